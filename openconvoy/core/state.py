"""Vehicle state: what a convoy member knows about itself and hears from the others.

Units are SI throughout; positions are local ENU metres around the convoy origin,
heading is radians with 0 = east and counter-clockwise positive (DESIGN.md, Conventions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace


@dataclass(frozen=True, slots=True)
class VehicleState:
    """One vehicle's state at time ``t``.

    Attributes:
        vehicle_id: convoy position, 0 = leader, 1 = first follower, ...
        t: time the state was measured, seconds on the shared clock.
        x, y: ENU position of the reference point (GPS antenna), metres.
        speed: forward speed, m/s (negative when reversing).
        heading: yaw, radians, 0 = east, counter-clockwise positive.
        accel: longitudinal acceleration, m/s².
        yaw_rate: rad/s, counter-clockwise positive.
        length, width: vehicle size, metres (0 = unknown).
    """

    vehicle_id: int
    t: float
    x: float
    y: float
    speed: float
    heading: float
    accel: float = 0.0
    yaw_rate: float = 0.0
    length: float = 0.0
    width: float = 0.0

    def extrapolate(self, t: float) -> VehicleState:
        """Dead-reckon this state to time ``t`` at constant speed and heading."""
        dt = t - self.t
        return replace(
            self,
            t=t,
            x=self.x + self.speed * math.cos(self.heading) * dt,
            y=self.y + self.speed * math.sin(self.heading) * dt,
        )

    def distance_to(self, other: VehicleState) -> float:
        """Euclidean distance between reference points, metres."""
        return math.hypot(self.x - other.x, self.y - other.y)


_PI = math.pi
_TWO_PI = 2.0 * math.pi


def wrap_angle(a: float) -> float:
    """Wrap an angle (rad) to [-π, π): ``(a + π) % 2π - π``, the modulo skipped where it
    changes nothing (within one turn) or adds one turn (one below): the same rounding at
    a tenth of the cost, which the batched kernels, calling this compiled, need."""
    x = a + _PI
    if 0.0 <= x < _TWO_PI:
        return x - _PI
    if -_TWO_PI <= x < 0.0:
        return (x + _TWO_PI) - _PI
    return x % _TWO_PI - _PI
