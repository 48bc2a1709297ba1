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


def reckoned_travel(
    speed_mps: float, age_s: float, fresh_age_s: float, decel_mps2: float
) -> tuple[float, float]:
    """How far (m) a vehicle heard at ``speed_mps`` has gone since a message ``age_s`` old,
    and its speed now (m/s): at constant speed up to ``fresh_age_s`` (s), beyond as if
    braking at ``decel_mps2`` (m/s²; inf: stopped where last heard) since the message.
    The batched kernels call this function compiled (``envs.vector.jit.rules``)."""
    if age_s <= fresh_age_s:
        return speed_mps * age_s, speed_mps
    a = decel_mps2
    if speed_mps > 0.0 and not math.isinf(a):
        tau = min(age_s, speed_mps / a)
        return speed_mps * tau - 0.5 * a * tau * tau, max(speed_mps - a * age_s, 0.0)
    return 0.0, 0.0


def dead_reckon(
    latest: VehicleState, now: float, fresh_age_s: float, stop_after_s: float, decel_mps2: float
) -> TargetEstimate | None:
    """``latest`` brought to ``now`` (s): at constant speed up to ``fresh_age_s``, braking
    at ``decel_mps2`` (inf: stopped where last heard) beyond; None past ``stop_after_s``."""
    age = max(now - latest.t, 0.0)
    if age > stop_after_s:
        return None
    h = latest.heading
    d, speed = reckoned_travel(latest.speed, age, fresh_age_s, decel_mps2)
    return TargetEstimate(
        latest.x + d * math.cos(h), latest.y + d * math.sin(h), speed, h, age, age > fresh_age_s
    )


def gap_and_closing(own: VehicleState, est: TargetEstimate) -> tuple[float, float]:
    """``(gap_m, closing_mps)`` from ``own`` to the estimated vehicle: centre to centre,
    and how fast it shrinks (positive = closing)."""
    # Velocities projected on the line between the two: the range rate, negated.
    vx = own.speed * math.cos(own.heading) - est.speed * math.cos(est.heading)
    vy = own.speed * math.sin(own.heading) - est.speed * math.sin(est.heading)
    return closing_m(est.x - own.x, est.y - own.y, vx, vy, own.speed, est.speed)


def closing_m(
    dx_m: float, dy_m: float, dvx_mps: float, dvy_mps: float, own_mps: float, est_mps: float
) -> tuple[float, float]:
    """``gap_and_closing`` on floats: the offset (m) to the other vehicle, the velocity
    difference (own minus other, m/s) and both speeds (m/s). The batched kernels call this
    function compiled (``envs.vector.jit.rules``)."""
    gap = math.hypot(dx_m, dy_m)
    if gap <= 0.0:
        return 0.0, max(own_mps - est_mps, 0.0)
    return gap, (dx_m * dvx_mps + dy_m * dvy_mps) / gap
