"""An in-process world for simulated MAVLink vehicles: what each one's forward rangefinder sees.

A simulated vehicle knows only its own state; a real rangefinder sees the others. When all
the simulated vehicles run in one process (the live tests), they register here and each
asks ``forward_range`` for the nearest other vehicle ahead within its sensor's range and
field of view: the distance from its front bumper to that vehicle's rear bumper. The
geometry is the simulator's (``core.ranging``). Metres, m/s, radians (ENU).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

from openconvoy.core.ranging import in_view, range_and_rate
from openconvoy.core.state import VehicleState


@dataclass(frozen=True)
class Body:
    """A registered vehicle: its true state (a callable, read when asked) and length (m)."""

    state: Callable[[], VehicleState]
    length_m: float


class SimWorld:
    """The simulated vehicles of one process, by a key (their MAVLink system id)."""

    def __init__(self) -> None:
        self._bodies: dict[int, Body] = {}
        self._lock = threading.Lock()

    def register(self, key: int, state: Callable[[], VehicleState], length_m: float) -> None:
        """Add (or replace) vehicle ``key``; ``state()`` gives its true ENU state."""
        with self._lock:
            self._bodies[key] = Body(state, length_m)

    def unregister(self, key: int) -> None:
        """Remove vehicle ``key`` (a stopped vehicle still stands there: keep it if so)."""
        with self._lock:
            self._bodies.pop(key, None)

    def forward_range(self, key: int, max_range_m: float) -> tuple[float, float] | None:
        """(front-bumper-to-rear-bumper distance m, its rate m/s) to the nearest other
        vehicle whose centre is in vehicle ``key``'s field of view and within
        ``max_range_m``; None when nothing is."""
        with self._lock:
            bodies = dict(self._bodies)
        me = bodies.pop(key)
        ego = me.state()
        best: tuple[float, float] | None = None
        for other in bodies.values():
            s = other.state()
            if not in_view(ego.x, ego.y, ego.heading, s.x, s.y):
                continue
            rng, rate = range_and_rate(
                ego.x, ego.y, ego.speed, ego.heading, s.x, s.y, s.speed, s.heading
            )
            bumper = rng - 0.5 * (me.length_m + other.length_m)
            if bumper > max_range_m or (best is not None and bumper >= best[0]):
                continue
            best = (max(bumper, 0.0), rate)
        return best


def distance_sensor_cm(
    reading: tuple[float, float] | None,
    max_range_m: float,
    noise_m: float,
    gauss: Callable[[], float],
) -> tuple[int, int, int]:
    """(min_distance, max_distance, current_distance) in cm for DISTANCE_SENSOR. Nothing in
    range reads max + 100 cm, as ArduPilot's lidar drivers (LightWare, Benewake:
    ``*_OUT_OF_RANGE_ADD_CM``) report it; a reading is clipped to the sensor's span."""
    min_cm, max_cm = 1, min(int(round(max_range_m * 100)), 65535 - 100)
    if reading is None:
        return min_cm, max_cm, max_cm + 100
    d = reading[0] + (noise_m * gauss() if noise_m > 0 else 0.0)
    cm = int(round(d * 100)) if math.isfinite(d) else max_cm + 100
    return min_cm, max_cm, min(max(cm, min_cm), max_cm + 100)
