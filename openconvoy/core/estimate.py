"""Where a heard vehicle is now, from its newest message: bounded dead reckoning (issue 10).

A message no older than the member's fresh age is dead-reckoned at constant speed; an
older one as if its sender had braked at its limit from the moment it was sent (it may
have: only slowing is safe to assume); older than the stop age it says nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from openconvoy.core.state import VehicleState


@dataclass(frozen=True, slots=True)
class TargetEstimate:
    """Where a heard vehicle is now by its newest message: ENU position (m), speed (m/s),
    heading (rad), message age (s), and ``stale`` (older than ``MemberConfig.fresh_age_s``)."""

    x: float
    y: float
    speed: float
    heading: float
    age: float
    stale: bool


def dead_reckon(
    latest: VehicleState, now: float, fresh_age_s: float, stop_after_s: float, decel_mps2: float
) -> TargetEstimate | None:
    """``latest`` brought to ``now`` (s): at constant speed up to ``fresh_age_s``, braking
    at ``decel_mps2`` (inf: stopped where last heard) beyond; None past ``stop_after_s``."""
    age = max(now - latest.t, 0.0)
    if age > stop_after_s:
        return None
    v, h = latest.speed, latest.heading
    if age <= fresh_age_s:
        d, speed, stale = v * age, v, False
    else:
        a = decel_mps2
        if v <= 0.0 or math.isinf(a):
            d, speed = 0.0, 0.0
        else:
            tau = min(age, v / a)
            d, speed = v * tau - 0.5 * a * tau * tau, max(v - a * age, 0.0)
        stale = True
    return TargetEstimate(
        latest.x + d * math.cos(h), latest.y + d * math.sin(h), speed, h, age, stale
    )


def gap_and_closing(own: VehicleState, est: TargetEstimate) -> tuple[float, float]:
    """``(gap_m, closing_mps)`` from ``own`` to the estimated vehicle: centre to centre,
    and how fast it shrinks (positive = closing)."""
    dx, dy = est.x - own.x, est.y - own.y
    gap = math.hypot(dx, dy)
    if gap <= 0.0:
        return 0.0, max(own.speed - est.speed, 0.0)
    # Velocities projected on the line between the two: the range rate, negated.
    vx = own.speed * math.cos(own.heading) - est.speed * math.cos(est.heading)
    vy = own.speed * math.sin(own.heading) - est.speed * math.sin(est.heading)
    return gap, (dx * vx + dy * vy) / gap
