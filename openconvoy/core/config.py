"""Strict typed configuration: nested frozen dataclasses from and to TOML-like dicts.

An unknown key is an error naming the key and where it sits, so a typo in a config file
never silently falls back to a default. Every value is checked against its field's
annotation before the dataclass is built: a string where a number or a list is expected
is an error naming the key and the type (never iterated character by character), and a
number must be finite and inside its field's declared ``Range``::

    @dataclass(frozen=True)
    class SafetyConfig:
        speed_cap_mps: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 5.0

A number without a declared range must still be finite. Errors are ``ConfigError``.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from openconvoy.core.errors import ConfigError, InputFileError, MissingFileError

T = TypeVar("T")


@dataclass(frozen=True)
class Range:
    """The allowed interval of a numeric config field (in the field's units).

    ``lo``/``hi`` None = unbounded on that side; ``lo_open``/``hi_open`` exclude the bound.
    ``allow_inf`` admits +inf (for "no limit" values); NaN is never allowed.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    allow_inf: bool = False

    def contains(self, x: float) -> bool:
        if math.isnan(x) or (math.isinf(x) and not (self.allow_inf and x > 0)):
            return False
        if self.lo is not None and (x < self.lo or (self.lo_open and x == self.lo)):
            return False
        return not (self.hi is not None and (x > self.hi or (self.hi_open and x == self.hi)))

    def describe(self, kind: str = "number") -> str:
        """The interval in words, e.g. ``a finite number in (0, 50]``."""
        left = "(" if self.lo is None or self.lo_open else "["
        num = (lambda v: f"{int(v)}") if kind == "integer" else (lambda v: f"{v:g}")
        lo = "-inf" if self.lo is None else num(self.lo)
        hi = "inf" if self.hi is None else num(self.hi)
        right = (
            "]"
            if (self.hi is None and self.allow_inf) or (self.hi is not None and not self.hi_open)
            else ")"
        )
        finite = "" if self.allow_inf or kind == "integer" else "finite "
        return f"{'an' if kind == 'integer' else 'a'} {finite}{kind} in {left}{lo}, {hi}{right}"


FINITE = Range()


def check_number(value: Any, where: str, rng: Range = FINITE, integer: bool = False) -> float | int:
    """``value`` as a number inside ``rng``, else ``ConfigError`` naming ``where`` and the range."""
    kind = "an integer" if integer else "a number"
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or (integer and not isinstance(value, int))
    ):
        raise ConfigError(f"{where}: expected {kind}, got {_describe(value)}")
    if not rng.contains(float(value)):
        allowed = rng.describe("integer" if integer else "number")
        raise ConfigError(f"{where}: {value!r} is out of range; allowed: {allowed}")
    return value


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``; nested dataclass fields take sub-tables.

    Each value is checked against the field's annotation (``bool``, ``int``, ``float``,
    ``str``, ``tuple[X, ...]``, ``list[X]``, ``Literal``, ``X | None``, nested dataclasses)
    and ``Range``; ``ConfigError`` names ``where.key``, what was given and what is allowed.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table, got {_describe(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; expected some of {', '.join(fields)}"
        )
    missing = [
        n
        for n, f in fields.items()
        if n not in data
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {', '.join(missing)}")
    hints = typing.get_type_hints(cls, include_extras=True)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        kwargs[name] = _convert(value, hints.get(name, Any), child(where, name))
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:  # the dataclass's own checks (__post_init__)
        msg = str(exc)
        key = msg.split(":", 1)[0]
        name = key.rsplit(".", 1)[-1]
        if name in fields:  # "key: why" or "table.key: why" -> "file: table.key: why"
            raise ConfigError(f"{child(where, name)}{msg[len(key) :]}") from None
        raise ConfigError(f"{where}: {msg}") from None


def check_fields(obj: Any, where: str = "") -> None:
    """Check a built dataclass's values against their annotations and ranges, as
    ``from_dict`` does (for a ``__post_init__``: objects built in code get the same
    checks as those read from files). ``ConfigError`` names ``where.key``."""
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        if f.init and f.name in hints:
            value = getattr(obj, f.name)
            if not dataclasses.is_dataclass(value):
                _convert(value, hints[f.name], child(where, f.name))


def child(where: str, key: str) -> str:
    """Where ``key`` sits below ``where``: ``lab.toml`` -> ``lab.toml: key``, then
    ``lab.toml: key.sub`` (a file's name, then the key's path inside it)."""
    if not where:
        return key
    return f"{where}.{key}" if ": " in where or not _looks_like_file(where) else f"{where}: {key}"


def _looks_like_file(where: str) -> bool:
    return "/" in where or "\\" in where or where.endswith((".toml", ".json", ".zip", ".npz"))


def _describe(value: Any) -> str:
    if isinstance(value, str):
        return f"the string {value!r}"
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, (list, tuple)):
        return f"a list {list(value)!r}"
    return f"{type(value).__name__} {value!r}"


_PLURAL = {bool: "booleans", int: "integers", float: "numbers", str: "strings"}
_SINGULAR = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _bare(hint: Any) -> Any:
    return typing.get_args(hint)[0] if typing.get_origin(hint) is typing.Annotated else hint


def _type_name(hint: Any) -> str:
    hint = _bare(hint)
    origin = typing.get_origin(hint)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if origin in (tuple, list):
        args = [_bare(a) for a in typing.get_args(hint) if a is not Ellipsis]
        if len(set(args)) == 1 and (origin is list or Ellipsis in typing.get_args(hint)):
            return f"a list of {_PLURAL.get(args[0], 'values')}"
        if len(set(args)) == 1:
            return f"a list of {len(args)} {_PLURAL.get(args[0], 'values')}"
        return (
            "a list" if not args else "a list of (" + ", ".join(_type_name(a) for a in args) + ")"
        )
    if isinstance(hint, types.UnionType) or origin is typing.Union:
        return " or ".join(_type_name(a) for a in typing.get_args(hint) if a is not type(None))
    if dataclasses.is_dataclass(hint):
        return "a table"
    return _SINGULAR.get(hint, getattr(hint, "__name__", str(hint)))


def _convert(value: Any, hint: Any, where: str) -> Any:
    """``value`` checked (and lists made tuples where the field is a tuple) for ``hint``."""
    rng = FINITE
    if typing.get_origin(hint) is typing.Annotated:
        hint, *extras = typing.get_args(hint)
        rng = next((e for e in extras if isinstance(e, Range)), FINITE)
    origin = typing.get_origin(hint)
    if hint is Any or hint is object:
        return value
    if isinstance(hint, types.UnionType) or origin is typing.Union:
        return _convert_union(value, hint, rng, where)
    if dataclasses.is_dataclass(hint):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return value
        return from_dict(hint, value, where)  # type: ignore[arg-type]
    if origin is typing.Literal:
        if value not in typing.get_args(hint) or isinstance(value, bool) != any(
            isinstance(a, bool) for a in typing.get_args(hint)
        ):
            raise ConfigError(f"{where}: expected {_type_name(hint)}, got {_describe(value)}")
        return value
    if origin in (tuple, list):
        return _convert_sequence(value, hint, rng, where)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {_describe(value)}")
        return value
    if hint is int:
        return check_number(value, where, rng, integer=True)
    if hint is float:
        return float(check_number(value, where, rng))
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {_describe(value)}")
        return value
    return value


def _convert_union(value: Any, hint: Any, rng: Range, where: str) -> Any:
    """``value`` for the first member of union ``hint`` it fits (None for ``X | None``)."""
    args = typing.get_args(hint)
    if value is None and type(None) in args:
        return None
    errors = []
    for arg in (a for a in args if a is not type(None)):
        try:
            return _convert(value, typing.Annotated[arg, rng] if rng is not FINITE else arg, where)
        except ConfigError as exc:
            errors.append(exc)
    if len(errors) == 1:
        raise errors[0]
    raise ConfigError(f"{where}: expected {_type_name(hint)}, got {_describe(value)}")


def _convert_sequence(value: Any, hint: Any, rng: Range, where: str) -> Any:
    """``value`` as the list or tuple ``hint`` wants, each item checked (``rng`` applies
    to every item)."""
    origin = typing.get_origin(hint)
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where}: expected {_type_name(hint)}, got {_describe(value)}")
    args = typing.get_args(hint)
    if origin is tuple and args and args[-1] is not Ellipsis:
        if len(value) != len(args):
            raise ConfigError(
                f"{where}: expected {len(args)} values ({_type_name(hint)}), got {len(value)}"
            )
        items = [
            _convert(v, typing.Annotated[a, rng] if rng is not FINITE else a, f"{where}[{i}]")
            for i, (v, a) in enumerate(zip(value, args))
        ]
    else:
        inner = args[0] if args else Any
        if rng is not FINITE:
            inner = typing.Annotated[inner, rng]
        items = [_convert(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
    return tuple(items) if origin is tuple else items


def to_dict(obj: Any) -> dict[str, Any]:
    """A dataclass as nested dicts, dropping ``None`` values (TOML has no null)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        if not f.init:
            continue
        value = getattr(obj, f.name)
        if value is None:
            continue
        out[f.name] = to_dict(value) if dataclasses.is_dataclass(value) else value
    return out


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, with a one-line error naming the file on bad syntax."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MissingFileError(f"no such file: {p}") from None
    except IsADirectoryError:
        raise InputFileError(f"{p}: is a directory, not a TOML file") from None
    except PermissionError:
        raise InputFileError(f"{p}: permission denied (cannot read it)") from None
    except UnicodeDecodeError:
        raise InputFileError(f"{p}: not a text file (TOML is UTF-8 text)") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(f"{p}: invalid TOML: {exc}") from None
    except RecursionError:  # e.g. thousands of nested arrays (D58)
        raise InputFileError(f"{p}: invalid TOML: nested too deeply") from None


def dumps_toml(data: dict[str, Any]) -> str:
    """Write nested dicts of scalars and lists as TOML (tables after scalars; a list of
    dicts as an array of tables, ``[[name]]``)."""
    lines: list[str] = []
    _dump_table(data, [], lines)
    return "\n".join(lines).strip() + "\n"


def _is_table_array(value: Any) -> bool:
    return (
        isinstance(value, (list, tuple)) and bool(value) and all(isinstance(v, dict) for v in value)
    )


def _key(key: str) -> str:
    """A bare TOML key where it may be one, else a quoted one (``"track-file:a.json"``)."""
    bare = key and all(c.isalnum() and c.isascii() or c in "-_" for c in key)
    return key if bare else _toml_value(key)


def _dump_table(
    data: dict[str, Any], path: list[str], lines: list[str], array: bool = False
) -> None:
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict) and not _is_table_array(v)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in data.items() if _is_table_array(v)}
    if array:
        lines.append(f"[[{'.'.join(path)}]]")
    elif path and scalars:
        lines.append(f"[{'.'.join(path)}]")
    for key, value in scalars.items():
        lines.append(f"{_key(key)} = {_toml_value(value)}")
    if scalars or array:
        lines.append("")
    for key, value in tables.items():
        _dump_table(value, [*path, _key(key)], lines)
    for key, items in arrays.items():
        for item in items:
            _dump_table(item, [*path, _key(key)], lines, array=True)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ConfigError(f"cannot write {type(value).__name__} to TOML")
