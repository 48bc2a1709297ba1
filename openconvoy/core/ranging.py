"""A forward ranging sensor's true reading: range and range rate between two vehicles.

Pure geometry, shared by the simulator (``envs.world``) and the simulated MAVLink vehicle
(``bridge.simvehicle.world``) so both worlds see the same sensor. Positions in metres (ENU),
speeds in m/s along the heading, headings in radians (ENU, counter-clockwise from east).
"""

from __future__ import annotations

import math

FIELD_OF_VIEW_RAD = math.radians(30.0)
"""Full horizontal field of view of the forward sensor (a lidar/radar cone, ±15°)."""


def range_and_rate(
    ego_x: float,
    ego_y: float,
    ego_speed: float,
    ego_heading: float,
    ahead_x: float,
    ahead_y: float,
    ahead_speed: float,
    ahead_heading: float,
) -> tuple[float, float]:
    """Centre-to-centre range (m) from the ego to the vehicle ahead and its rate of change
    (m/s, negative = closing): the relative velocity projected on the line of sight."""
    dx, dy = ahead_x - ego_x, ahead_y - ego_y
    rng_m = math.hypot(dx, dy)
    if rng_m <= 0.0:
        return 0.0, 0.0
    dvx = ahead_speed * math.cos(ahead_heading) - ego_speed * math.cos(ego_heading)
    dvy = ahead_speed * math.sin(ahead_heading) - ego_speed * math.sin(ego_heading)
    return rng_m, (dx * dvx + dy * dvy) / rng_m


def in_view(
    ego_x: float,
    ego_y: float,
    ego_heading: float,
    x: float,
    y: float,
    fov_rad: float = FIELD_OF_VIEW_RAD,
) -> bool:
    """Is the point ``(x, y)`` ahead of the ego within the sensor's horizontal field of view?"""
    bearing = math.atan2(y - ego_y, x - ego_x) - ego_heading
    bearing = (bearing + math.pi) % (2.0 * math.pi) - math.pi
    return abs(bearing) <= 0.5 * fov_rad
