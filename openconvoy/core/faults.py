"""Fault injection: one vocabulary for the simulator (``sim --fault``) and the live tests.

A fault is ``KIND:VEHICLE@T_S``: vehicle ``VEHICLE`` (0 = leader) fails ``T_S`` seconds
into the run, for good. Kinds:

- ``halt``: the vehicle brakes to rest at its limit and stays there, still broadcasting
  (an autopilot switched to HOLD, a person on the brake);
- ``silent``: it stops broadcasting and keeps driving its commands (a dead radio);
- ``dead``: it brakes to rest and stops broadcasting (a crashed computer);
- ``forge``: a station without the convoy's keys starts broadcasting messages that claim
  to be the vehicle, 1 km ahead of it (``envs.forgery``); members that authenticate
  messages (the default) reject and count them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

from openconvoy.core.errors import ConfigError

FAULT_KINDS = ("halt", "silent", "dead", "forge")
FAULT_SYNTAX = "KIND:VEHICLE@T_S with KIND one of halt, silent, dead, forge (e.g. dead:0@30)"


@dataclass(frozen=True)
class Fault:
    """``kind`` (``FAULT_KINDS``) of vehicle ``vehicle`` from time ``t_s`` (s) on."""

    kind: str
    vehicle: int
    t_s: float

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ConfigError(
                f"unknown fault kind {self.kind!r}; expected one of {', '.join(FAULT_KINDS)}"
            )
        if isinstance(self.vehicle, bool) or not isinstance(self.vehicle, int) or self.vehicle < 0:
            raise ConfigError(f"fault vehicle must be an index >= 0, got {self.vehicle!r}")
        if (
            isinstance(self.t_s, bool)
            or not isinstance(self.t_s, (int, float))
            or not (math.isfinite(self.t_s) and self.t_s >= 0)
        ):
            raise ConfigError(
                f"fault time must be a finite number of seconds >= 0, got {self.t_s!r}"
            )

    @property
    def brakes(self) -> bool:
        """The vehicle brakes to rest (``halt``, ``dead``)."""
        return self.kind in ("halt", "dead")

    @property
    def mutes(self) -> bool:
        """The vehicle stops broadcasting (``silent``, ``dead``)."""
        return self.kind in ("silent", "dead")

    @property
    def forges(self) -> bool:
        """A forger claims to be the vehicle (``forge``)."""
        return self.kind == "forge"

    def active(self, t: float) -> bool:
        return t >= self.t_s - 1e-9

    def __str__(self) -> str:
        return f"{self.kind}:{self.vehicle}@{self.t_s:g}"


def parse_fault(spec: str) -> Fault:
    """``"dead:0@30"`` -> ``Fault("dead", 0, 30.0)``; a bad spec raises ConfigError (a ValueError) with one
    line naming it and the syntax."""
    text = spec.strip()
    kind, sep, rest = text.partition(":")
    vehicle, sep2, t = rest.partition("@")
    try:
        if not (sep and sep2):
            raise ConfigError("missing ':' or '@'")
        return Fault(kind.strip(), int(vehicle), float(t))
    except ValueError as exc:
        raise ConfigError(f"bad fault {spec!r}: {exc}; expected {FAULT_SYNTAX}") from None


def check_faults(faults: tuple[Fault, ...], n_vehicles: int) -> None:
    """Raise ValueError when a fault names a vehicle the convoy does not have."""
    for f in faults:
        if f.vehicle >= n_vehicles:
            raise ConfigError(
                f"fault {f}: no vehicle {f.vehicle} in a convoy of {n_vehicles} (0..{n_vehicles - 1})"
            )


def check_fault_times(faults: tuple[Fault, ...], duration_s: float) -> None:
    """Raise ConfigError (one line) for a fault set after the run ends at ``duration_s``
    (s): it would never happen, and a robustness study that injects nothing is wrong."""
    for f in faults:
        if not f.t_s <= duration_s:
            raise ConfigError(
                f"fault {f}: at {f.t_s:g} s, after the run ends at {duration_s:g} s "
                "(it would never happen)"
            )


AUTH_MODES = ("required", "off")
"""Whether members authenticate messages (``required``: forged ones are rejected)."""


def fault_specs(specs: Iterable[str]) -> tuple[str, ...]:
    """Fault specs normalized (``halt:1@30.0`` -> ``halt:1@30``), as every config keeps
    them; a bad one raises ``parse_fault``'s ConfigError."""
    return tuple(str(parse_fault(f)) for f in specs)


def check_auth(auth: str, key: str = "auth") -> None:
    """Raise ConfigError (one line naming ``key``) unless ``security.auth`` is in ``AUTH_MODES``."""
    if auth not in AUTH_MODES:
        raise ConfigError(f"{key} must be 'required' or 'off', got {auth!r}")
