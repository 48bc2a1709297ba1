"""Plug-ins: a researcher's own Python objects named in a spec or a config file.

A *reference* names a Python object::

    mylab.spacing:Quadratic          a module on the import path (the current directory too)
    path/to/spacing.py:Quadratic     a file (relative to the current directory)
    quadratic                        a name an installed package registers under an
                                     entry-point group (``ENTRY_POINT_GROUPS``)

and may carry keyword arguments, ``REF?key=value&key=value`` (values read as TOML scalars:
``0.5``, ``3``, ``true``, ``"text"``; a bare word is a string). The object is a class or a
factory, called with those keyword arguments (and the parameters a config table gives it).

Every failure here is one line naming what is wrong (``ConfigError``): a missing file or
module, a missing name, keyword arguments the object does not take, a constructor that
raised, a missing method or one whose signature the platform cannot call. This module
imports nothing of ours but ``core.errors`` (plug-in code is the user's).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import os
import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from openconvoy.core.errors import ConfigError

ENTRY_POINT_GROUPS: dict[str, str] = {
    "policy": "openconvoy.policies",
    "spacing": "openconvoy.spacing",
    "trigger": "openconvoy.triggers",
    "topology": "openconvoy.topologies",
    "speed": "openconvoy.speed_controllers",
    "heading": "openconvoy.heading_controllers",
    "reward": "openconvoy.rewards",
    "features": "openconvoy.features",
}
"""Entry-point group of each kind of plug-in (``[project.entry-points."openconvoy.policies"]``
in a package's ``pyproject.toml``: ``name = "module:Name"``)."""

_IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
_MODULE = re.compile(rf"^{_IDENT}(\.{_IDENT})*$")
_NAME = re.compile(rf"^{_IDENT}$")


def split_args(spec: str) -> tuple[str, dict[str, Any]]:
    """``REF?k=v&k2=v2`` -> ``(REF, {k: v, k2: v2})`` (values as TOML scalars)."""
    if "?" not in spec:
        return spec, {}
    ref, _, query = spec.partition("?")
    args: dict[str, Any] = {}
    for item in query.split("&"):
        if not item:
            continue
        key, eq, text = item.partition("=")
        if not eq or not _NAME.match(key.strip()):
            raise ConfigError(f"{spec}: plug-in argument {item!r} is not key=value")
        args[key.strip()] = parse_value(text.strip())
    return ref, args


def parse_value(text: str) -> Any:
    """A ``key=value`` value as TOML reads a scalar (``0.5``, ``3``, ``true``, ``"a"``);
    any other text is taken as a string."""
    import tomllib

    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def join_args(ref: str, args: Mapping[str, Any]) -> str:
    """The spec ``split_args`` reads back to ``(ref, args)`` (existing arguments of
    ``ref`` kept, ``args`` overriding them)."""
    base, old = split_args(ref)
    merged = {**old, **args}
    if not merged:
        return base
    return base + "?" + "&".join(f"{k}={_value_text(v)}" for k, v in merged.items())


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value if parse_value(value) == value and "&" not in value else f'"{value}"'
    return repr(value)


def is_reference(text: str) -> bool:
    """``text`` looks like ``module.path:Name`` or ``file.py:Name`` (arguments allowed)."""
    ref = split_args(text)[0]
    left, colon, name = ref.rpartition(":")
    if not colon or not _NAME.match(name):
        return False
    return left.endswith(".py") or bool(_MODULE.match(left))


def file_of(text: str) -> str | None:
    """The ``.py`` file a ``file.py:Name`` reference names, else None."""
    ref = split_args(text)[0]
    left, colon, _ = ref.rpartition(":")
    return left if colon and left.endswith(".py") else None


def load_object(ref: str, where: str) -> Any:
    """The object ``module:Name`` or ``file.py:Name`` names (arguments ignored)."""
    ref = split_args(ref)[0]
    left, _, name = ref.rpartition(":")
    module = _load_file(left, where) if left.endswith(".py") else _import(left, where)
    try:
        return getattr(module, name)
    except AttributeError:
        raise ConfigError(f"{where}: {left} has no {name!r}") from None


def _import(module: str, where: str) -> Any:
    # As ``python -m`` and uvicorn do: a module beside the user is importable.
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.append(cwd)
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and module.startswith(exc.name):
            raise ConfigError(f"{where}: no module named {exc.name!r}") from None
        raise ConfigError(f"{where}: importing {module} failed: {_line(exc)}") from None
    except Exception as exc:  # noqa: BLE001 - the user's module: one line, not a traceback
        raise ConfigError(f"{where}: importing {module} failed: {_line(exc)}") from None


def _load_file(path: str, where: str) -> Any:
    """A ``.py`` file as a module, once per resolved path (``sys.modules`` keeps it, so
    its classes pickle within this process and deep-copy everywhere)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"{where}: no such file {path}")
    resolved = str(p.resolve())
    name = "openconvoy_plugin_" + p.stem + "_" + hashlib.sha1(resolved.encode()).hexdigest()[:10]
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, resolved)
    if spec is None or spec.loader is None:
        raise ConfigError(f"{where}: cannot load {path} as Python")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # noqa: BLE001 - the user's file: one line, not a traceback
        del sys.modules[name]
        raise ConfigError(f"{where}: loading {path} failed: {_line(exc)}") from None
    return module


def entry_points(kind: str) -> dict[str, Any]:
    """Installed packages' plug-ins of ``kind`` (``ENTRY_POINT_GROUPS``): name -> entry point."""
    from importlib.metadata import entry_points as _eps

    return {ep.name: ep for ep in _eps(group=ENTRY_POINT_GROUPS[kind])}


def resolve(spec: str, kind: str, where: str) -> tuple[Any, dict[str, Any]]:
    """The object a reference or an entry-point name of ``kind`` names, and the keyword
    arguments the spec carries."""
    ref, args = split_args(spec)
    if is_reference(ref):
        return load_object(ref, where), args
    eps = entry_points(kind)
    if ref in eps:
        try:
            return eps[ref].load(), args
        except Exception as exc:  # noqa: BLE001 - the installed package's code
            raise ConfigError(
                f"{where}: loading entry point {ref!r} failed: {_line(exc)}"
            ) from None
    raise ConfigError(
        f"{where}: {ref!r} is neither module:Name, file.py:Name nor an installed {kind} plug-in"
    )


def construct(obj: Any, kwargs: Mapping[str, Any], where: str) -> Any:
    """``obj(**kwargs)`` (a class or a factory), its keyword arguments checked first."""
    label = getattr(obj, "__qualname__", repr(obj))
    if not callable(obj):
        raise ConfigError(f"{where}: {label} is not a class or a factory")
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):
        signature = None
    if signature is not None:
        try:
            signature.bind(**kwargs)
        except TypeError as exc:
            raise ConfigError(
                f"{where}: {label}{_bare(signature)} cannot take {dict(kwargs)}: {exc}"
            ) from None
    try:
        return obj(**kwargs)
    except Exception as exc:  # noqa: BLE001 - the user's constructor
        raise ConfigError(f"{where}: {label}(**{dict(kwargs)}) raised {_line(exc)}") from None


def check_methods(obj: Any, methods: Mapping[str, int], where: str) -> None:
    """Each method of ``methods`` (name -> number of positional arguments the platform
    passes) exists on ``obj`` and takes that many; else one line naming it."""
    label = type(obj).__name__
    for name, n_args in methods.items():
        method = getattr(obj, name, None)
        if method is None or not callable(method):
            raise ConfigError(f"{where}: {label} has no method {name}() (the protocol needs it)")
        try:
            signature = inspect.signature(method)
        except (TypeError, ValueError):
            continue
        try:
            signature.bind(*([None] * n_args))
        except TypeError:
            raise ConfigError(
                f"{where}: {label}.{name}{_bare(signature)} cannot be called with {n_args} "
                f"argument{'s' if n_args != 1 else ''} (the protocol passes {n_args})"
            ) from None


def tunable(obj: Any) -> dict[str, tuple[float, float]]:
    """A plug-in's declared tunable parameters: its ``tunable`` attribute, a mapping of
    keyword-argument name -> ``(low, high)`` (``openconvoy tune`` searches them)."""
    declared = getattr(obj, "tunable", None) or {}
    out: dict[str, tuple[float, float]] = {}
    for name, bounds in dict(declared).items():
        lo, hi = (float(b) for b in bounds)
        out[str(name)] = (lo, hi)
    return out


def _bare(signature: inspect.Signature) -> inspect.Signature:
    """``signature`` without its return annotation (for messages)."""
    return signature.replace(return_annotation=inspect.Signature.empty)


def _line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


__all__ = [
    "COMPONENT_METHODS",
    "ENTRY_POINT_GROUPS",
    "component",
    "component_tunable",
    "check_methods",
    "construct",
    "entry_points",
    "file_of",
    "is_reference",
    "join_args",
    "load_object",
    "resolve",
    "split_args",
    "tunable",
]


COMPONENT_METHODS: dict[str, dict[str, int]] = {
    "spacing": {"pair_gap": 3},
    "trigger": {"should_send": 3},
    "topology": {"keeps": 3},
    "speed": {"__call__": 3},
    "heading": {"__call__": 4},
}
"""The methods each kind of component plug-in must have, with the number of positional
arguments the platform passes (``core.components`` documents each protocol)."""


def component(kind: str, spec: str, params: Mapping[str, Any], where: str, **extra: Any) -> Any:
    """A component plug-in of ``kind`` built from ``spec`` (reference or entry-point name,
    its ``?k=v`` arguments) and the config's ``params``, its methods checked. ``extra``
    keyword arguments (``dt_s`` for a speed controller) pass only where the constructor
    names them."""
    obj, args = resolve(spec, kind, where)
    kwargs = {**args, **params}
    if extra:
        try:
            names: Mapping[str, Any] = inspect.signature(obj).parameters
        except (TypeError, ValueError):
            names = {}
        kwargs.update({k: v for k, v in extra.items() if k in names and k not in kwargs})
    instance = construct(obj, kwargs, where)
    check_methods(instance, COMPONENT_METHODS[kind], where)
    return instance


def features(spec: str, size: int, where: str) -> tuple[Any, int]:
    """An observation-features plug-in (``features`` group) built from ``spec`` and how
    many numbers it appends to an observation of ``size``: an object called
    ``(observation) -> 1-D array`` of a fixed length (checked on a zero observation)."""
    import numpy as np

    obj, args = resolve(spec, "features", where)
    fn = construct(obj, args, where)
    check_methods(fn, {"__call__": 1}, where)
    try:
        out = np.asarray(fn(np.zeros(size, dtype=np.float32)), dtype=np.float32)
    except Exception as exc:  # noqa: BLE001 - the plug-in's code
        raise ConfigError(f"{where}: on a zero observation it raised {_line(exc)}") from None
    if out.ndim != 1:
        raise ConfigError(f"{where}: returns shape {out.shape}; expected a 1-D array")
    return fn, int(out.shape[0])


def component_tunable(kind: str, spec: str, where: str) -> dict[str, tuple[float, float]]:
    """The tunable parameters a component plug-in's class declares (``tunable``)."""
    return tunable(resolve(spec, kind, where)[0])
