"""The staleness ladder: cooperate, degrade, stop, by the age of the messages needed.

Messages older than ``degrade_after_s`` switch the vehicle to degraded mode, ACC-like
following on the range to the vehicle ahead with a wider time gap; older than
``stop_after_s`` command a stop; fresh messages bring it back. The same in both worlds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError

COOP, DEGRADED, STOP = "coop", "degraded", "stop"


@dataclass(frozen=True)
class LadderConfig:
    """``enabled``; ages in seconds; ``extra_headway_s`` widens the desired gap by that
    many seconds of ego speed in degraded mode; ``gap_gain`` (1/s) of the ACC law;
    ``intruder_margin_m``: the ranging sensor's target takes over (``ranging_override``)
    when it is this much closer than the predecessor by its messages or the desired gap."""

    enabled: bool = False
    degrade_after_s: Annotated[float, Range(0.0, 600.0, lo_open=True)] = 0.5
    stop_after_s: Annotated[float, Range(0.0, 600.0, lo_open=True)] = 2.0
    extra_headway_s: Annotated[float, Range(0.0, 60.0)] = 1.0
    gap_gain: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 0.5
    intruder_margin_m: Annotated[float, Range(0.0, 1000.0)] = 3.0

    def __post_init__(self) -> None:
        if not 0 < self.degrade_after_s < self.stop_after_s:
            raise ConfigError(
                "staleness ladder needs 0 < degrade_after_s < stop_after_s, got "
                f"{self.degrade_after_s} and {self.stop_after_s}"
            )
        if not self.intruder_margin_m >= 0:
            raise ConfigError(
                f"staleness ladder needs intruder_margin_m >= 0, got {self.intruder_margin_m}"
            )


def rung(age_s: float, config: LadderConfig) -> str:
    """The mode for messages of age ``age_s`` (inf = never heard)."""
    if not config.enabled:
        return COOP
    return MODES[rung_code(age_s, config.degrade_after_s, config.stop_after_s)]


MODES = (COOP, DEGRADED, STOP)
"""The rungs by code (``rung_code``)."""


def rung_code(age_s: float, degrade_after_s: float, stop_after_s: float) -> int:
    """The rung for messages of age ``age_s`` (s; inf = never heard) as its index in
    ``MODES``: 0 up to ``degrade_after_s``, 1 up to ``stop_after_s``, else 2. The batched
    kernels call this function compiled (``envs.vector.jit.rules``)."""
    if age_s <= degrade_after_s:
        return 0
    if age_s <= stop_after_s:
        return 1
    return 2


def ranging_override(
    range_m: float, v2v_gap_m: float, desired_gap_m: float, config: LadderConfig
) -> bool:
    """True when the ranging sensor's target (``range_m``, centre to centre) is closer by more
    than ``intruder_margin_m`` than the predecessor by its messages (``v2v_gap_m``:
    something without V2V is in the gap, a cut-in) or than the desired gap (the cooperative
    controller is not keeping its distance): the vehicle then follows by ranging (degraded).
    Never with the ladder off."""
    return config.enabled and intruder_closer(
        range_m, v2v_gap_m, desired_gap_m, config.intruder_margin_m
    )


def intruder_closer(
    range_m: float, v2v_gap_m: float, desired_gap_m: float, intruder_margin_m: float
) -> bool:
    """``ranging_override``'s test on floats (m): the ranging target is closer by more than
    the margin than both the V2V gap and the desired gap. The batched kernels call this
    function compiled (``envs.vector.jit.rules``)."""
    return range_m < max(v2v_gap_m, desired_gap_m) - intruder_margin_m


def acc_speed(
    range_m: float,
    range_rate_mps: float,
    ego_speed_mps: float,
    desired_gap_m: float,
    config: LadderConfig,
) -> float:
    """Degraded-mode speed setpoint (m/s): match the vehicle ahead and close the gap error
    to ``desired_gap_m`` widened by ``extra_headway_s``; never negative."""
    return acc_speed_mps(
        range_m,
        range_rate_mps,
        ego_speed_mps,
        desired_gap_m,
        config.extra_headway_s,
        config.gap_gain,
    )


def acc_speed_mps(
    range_m: float,
    range_rate_mps: float,
    ego_speed_mps: float,
    desired_gap_m: float,
    extra_headway_s: float,
    gap_gain: float,
) -> float:
    """``acc_speed`` on floats (``LadderConfig``'s two numbers: s, 1/s). The batched
    kernels call this function compiled (``envs.vector.jit.rules``)."""
    target_gap = desired_gap_m + extra_headway_s * max(ego_speed_mps, 0.0)
    v_ahead = ego_speed_mps + range_rate_mps
    return max(0.0, v_ahead + gap_gain * (range_m - target_gap))
