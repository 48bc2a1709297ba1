"""Whole policies from Python: ``--policy module.path:Name``, ``file.py:Name``, an entry point.

``Name`` is a class or a factory, called with keyword arguments (the spec's ``?k=v``, a
policy TOML's ``[policy.args]``, ``--policy-arg key=value``); what it returns needs only
``act(observation) -> [speed_mps, heading_change_rad]``. ``reset([seed])``,
``member_config`` (a ``MemberConfig``; default: the scenario's), ``control_rate_hz`` (Hz;
default 20), ``name`` and ``act_batch`` are optional (``core.policy`` says what is called
when). Everything is checked here, at load time, each failure one line naming it
(``ConfigError``; the CLI exits 2): a missing ``act``, a method whose signature the
platform cannot call, a member config that is not one, a control rate that is not a
positive number.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from openconvoy.core import plugins
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import MemberConfig

DEFAULT_RATE_HZ = 20.0


class PluginPolicy:
    """A user's policy object as the worlds run it (a ``ConvoyPolicy``): its ``act``
    called as is, the optional parts given their defaults."""

    def __init__(self, inner: Any, label: str) -> None:
        self.inner = inner
        self.label = label
        self._reset_takes_seed = _reset_arity(inner, label)

    @property
    def member_config(self) -> MemberConfig | None:
        return getattr(self.inner, "member_config", None)

    @property
    def control_rate_hz(self) -> float:
        return float(getattr(self.inner, "control_rate_hz", DEFAULT_RATE_HZ))

    @property
    def name(self) -> str:
        return str(getattr(self.inner, "name", None) or self.label)

    def reset(self, seed: int | None = None) -> None:
        if self._reset_takes_seed is None:
            return
        if self._reset_takes_seed:
            self.inner.reset(seed)
        else:
            self.inner.reset()

    def act(self, observation: np.ndarray) -> np.ndarray:
        return self.inner.act(observation)


class BatchPluginPolicy(PluginPolicy):
    """A ``PluginPolicy`` whose object also has ``act_batch`` (``core.policy.BatchPolicy``)."""

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        return np.asarray(self.inner.act_batch(observations), dtype=np.float32)

    def reset_rows(self, rows: np.ndarray) -> None:
        """Forget the rows' memories (the object's ``reset_rows``, if it has one)."""
        fn = getattr(self.inner, "reset_rows", None)
        if callable(fn):
            fn(rows)


def load_plugin_policy(
    spec: str, kwargs: Mapping[str, Any] | None = None, label: str | None = None
) -> PluginPolicy:
    """The policy ``spec`` (``module:Name``, ``file.py:Name`` or an ``openconvoy.policies``
    entry point, with ``?k=v`` arguments) names, built with ``kwargs`` too and checked."""
    where = f"policy {spec}"
    obj, args = plugins.resolve(spec, "policy", where)
    inner = plugins.construct(obj, {**args, **(kwargs or {})}, where)
    return check_policy_object(inner, label or plugins.split_args(spec)[0], where)


def check_policy_object(inner: Any, label: str, where: str) -> PluginPolicy:
    """``inner`` wrapped as a ``PluginPolicy`` once everything it declares is right."""
    plugins.check_methods(inner, {"act": 1}, where)
    methods = {"act_batch": 1} if callable(getattr(inner, "act_batch", None)) else {}
    plugins.check_methods(inner, methods, where)
    mc = getattr(inner, "member_config", None)
    if mc is not None and not isinstance(mc, MemberConfig):
        raise ConfigError(
            f"{where}: member_config is a {type(mc).__name__}, not an "
            "openconvoy.core.member.MemberConfig (or None: the scenario's)"
        )
    rate = getattr(inner, "control_rate_hz", DEFAULT_RATE_HZ)
    if (
        isinstance(rate, bool)
        or not isinstance(rate, (int, float))
        or not math.isfinite(rate)
        or not 0 < rate <= 100
    ):
        raise ConfigError(f"{where}: control_rate_hz is {rate!r}; expected a number in (0, 100] Hz")
    cls = BatchPluginPolicy if methods else PluginPolicy
    return cls(inner, label)


def _reset_arity(inner: Any, where: str) -> bool | None:
    """Whether ``inner.reset`` takes the seed (True), nothing (False), or is absent (None)."""
    fn = getattr(inner, "reset", None)
    if fn is None:
        return None
    if not callable(fn):
        raise ConfigError(f"policy {where}: reset is not a method")
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return True
    for args in ((None,), ()):
        try:
            sig.bind(*args)
            return bool(args)
        except TypeError:
            continue
    raise ConfigError(
        f"policy {where}: {type(inner).__name__}.reset{sig} cannot be called as reset(seed) or reset()"
    )


def installed_policies() -> dict[str, str]:
    """Policies installed packages register (``openconvoy.policies`` entry points):
    name -> ``module:Name``."""
    return {name: ep.value for name, ep in sorted(plugins.entry_points("policy").items())}


def tunable_of(spec: str) -> dict[str, tuple[float, float]]:
    """The keyword arguments a policy plug-in declares tunable (``tunable``: name ->
    ``(low, high)``), for ``openconvoy tune``."""
    obj, _ = plugins.resolve(spec, "policy", f"policy {spec}")
    return plugins.tunable(obj)
