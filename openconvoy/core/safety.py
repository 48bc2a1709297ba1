"""The braking-aware minimum gap: the emergency-stop rule, the same in sim and on vehicles.

A follower must stop when the gap to the vehicle ahead, between bumpers, less the
distance it needs to shed the closing speed at its braking limit (``v²/(2·a)``, plus the
reaction delay times the closing speed), falls below a margin. A fixed centre-to-centre
minimum (1 m once) leaves 0.13 m between the bumpers of the small cars and no room to
brake at all (issue 10). ``envs.convoy_env`` and ``bridge.failsafes.Envelope`` both use
``BrakingGap``; the numbers come from the vehicle preset (``for_vehicle``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from openconvoy.core.errors import ConfigError

DEFAULT_MARGIN_LENGTHS = 0.25
"""Default margin between bumpers, in own vehicle lengths: 0.19-0.24 m for the small cars,
1.2 m for a car (below the 2 m CACC standstill distance, so a convoy at rest is not an
emergency)."""


def bumper_gap(centre_gap_m: float, ego_length_m: float, pred_length_m: float) -> float:
    """Gap between bumpers (m) from the centre-to-centre gap and the two lengths."""
    return centre_gap_m - 0.5 * (ego_length_m + pred_length_m)


@dataclass(frozen=True)
class BrakingGap:
    """The rule's numbers, SI.

    Attributes:
        decel_mps2: the ego's braking limit (m/s², positive).
        reaction_s: time from deciding to brake to braking at the limit (actuation delay
            plus the speed loop's lag, s).
        margin_m: the stop fires when the clearance left after braking is below this (m,
            between bumpers).
    """

    decel_mps2: float
    reaction_s: float
    margin_m: float

    def __post_init__(self) -> None:
        for name in ("decel_mps2", "reaction_s", "margin_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"braking gap {name} must be a finite number, got {value!r}")
        if self.decel_mps2 <= 0 or self.reaction_s < 0 or self.margin_m < 0:
            raise ConfigError(
                "braking gap needs decel_mps2 > 0, reaction_s >= 0 and margin_m >= 0, got "
                f"{self.decel_mps2}, {self.reaction_s}, {self.margin_m}"
            )

    def stopping_distance(self, closing_mps: float) -> float:
        """Distance (m) the gap shrinks before the closing speed (m/s, positive = closing)
        is shed: reaction delay, then braking at the limit. 0 when opening."""
        if not closing_mps > 0.0:
            return 0.0
        return closing_mps * closing_mps / (2.0 * self.decel_mps2) + self.reaction_s * closing_mps

    def clearance(self, bumper_gap_m: float, closing_mps: float) -> float:
        """Bumper gap left (m) after braking now from ``closing_mps``."""
        return bumper_gap_m - self.stopping_distance(closing_mps)

    def too_close(self, bumper_gap_m: float, closing_mps: float) -> bool:
        """True when the gap is known and the clearance left is below the margin."""
        if not math.isfinite(bumper_gap_m):
            return False
        closing = closing_mps if math.isfinite(closing_mps) else 0.0
        return self.clearance(bumper_gap_m, closing) < self.margin_m

    def reason(self, bumper_gap_m: float, closing_mps: float) -> str:
        """The log line: gap, closing speed and what braking would leave."""
        return (
            f"gap {bumper_gap_m:.2f} m between bumpers closing at {closing_mps:.2f} m/s leaves "
            f"{self.clearance(bumper_gap_m, closing_mps):.2f} m after braking (margin {self.margin_m:.2f} m)"
        )


def for_vehicle(
    decel_max_mps2: float,
    actuation_delay_s: float,
    speed_lag_s: float,
    length_m: float,
    margin_m: float | None = None,
) -> BrakingGap:
    """The rule for a vehicle preset's numbers; ``margin_m`` None = the default
    (``DEFAULT_MARGIN_LENGTHS`` of the vehicle's length)."""
    margin = DEFAULT_MARGIN_LENGTHS * length_m if margin_m is None else margin_m
    return BrakingGap(decel_max_mps2, actuation_delay_s + speed_lag_s, margin)
