"""IdealLink: a ``VehicleLink`` without an autopilot behind it — the vehicle goes at once
where its setpoints say (speed and heading exact, position integrated on the injected
clock). For runner tests and benchmarks, and the second implementation that keeps the
``VehicleLink`` protocol honest (``tests/bridge/test_link_contract.py`` holds it and
``MavlinkLink`` to the same contract)."""

from __future__ import annotations

import math
from collections.abc import Callable

from openconvoy.bridge.link import Autopilot, LinkLost, StatusCallback, Telemetry
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.core.state import VehicleState

GUIDED, HOLD = "GUIDED", "HOLD"


class IdealLink:
    """Vehicle ``vehicle_id`` at ENU ``(x, y)`` (m) heading ``heading`` (rad), at rest.

    ``clock`` is the link clock (s, monotonic), ``wall`` the shared clock stamped on the
    telemetry (s); ``move`` False keeps it where it is whatever it is told. One state
    behind everything, so the link is its own ``setpoints`` and ``modes``.
    """

    telemetry_timeout_s = 0.5
    heartbeat_timeout_s = 3.0

    def __init__(
        self,
        clock: Callable[[], float],
        wall: Callable[[], float],
        origin: Origin,
        vehicle_id: int,
        x: float = 0.0,
        y: float = 0.0,
        heading: float = 0.0,
        move: bool = True,
        autopilot: Autopilot = "ardupilot",
    ) -> None:
        self.clock, self.wall, self.origin, self.vehicle_id = clock, wall, origin, vehicle_id
        self.x, self.y, self.heading, self.speed = x, y, heading, 0.0
        self.move = move
        self.telemetry_rates: dict[str, float] = {}
        self.sent: list[tuple[float, float, float]] = []
        self.armed = False
        self.mode = HOLD
        self.holds = 0
        self.pilot_took_over = False
        self.takeover_reason = ""
        self.failsafe_took_over = False
        self.lost = True  # until connected
        self.setpoints = self
        self.modes = self
        self._autopilot = autopilot
        self._t = clock()

    @property
    def autopilot(self) -> Autopilot:
        return self._autopilot

    def connect(self, timeout_s: float) -> None:
        self.lost = False
        self.telemetry_rates = {"GLOBAL_POSITION_INT": 20.0}
        self._t = self.clock()

    def reconnect(self, timeout_s: float) -> None:
        self.connect(timeout_s)

    def poll(self) -> Telemetry | None:
        if self.lost:
            return None
        now = self.clock()
        if self.move:
            dt = now - self._t
            self.x += self.speed * math.cos(self.heading) * dt
            self.y += self.speed * math.sin(self.heading) * dt
        self._t = now
        lat, lon, _ = enu_to_geodetic(self.origin, self.x, self.y)
        st = VehicleState(self.vehicle_id, self.wall(), self.x, self.y, self.speed, self.heading)
        return Telemetry(st, float(lat), float(lon), self.mode, self.armed, now, now)

    def prepare_and_arm(self, timeout_s: float, on_status: StatusCallback | None = None) -> None:
        if self.lost:
            raise LinkLost("not connected")
        self.mode, self.armed = GUIDED, True

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        if self.pilot_took_over or self.lost:
            return False
        self.sent.append((self.clock(), speed_mps, heading_rad))
        self.speed, self.heading = speed_mps, heading_rad
        return True

    def stop(self) -> bool:
        return self.send(0.0, self.heading)

    def hold(self, timeout_s: float = 2.0) -> None:
        self.holds += 1
        self.speed, self.mode = 0.0, HOLD

    def disarm(self, timeout_s: float = 2.0) -> None:
        self.armed = False

    def close(self) -> None:
        self.lost = True
