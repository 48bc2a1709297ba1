"""Telemetry intake for ``MavlinkLink``: GLOBAL_POSITION_INT and ATTITUDE -> ``Telemetry``.

MAVLink's NED and integer encodings end here: positions become ENU metres around the
convoy origin, headings ENU radians (0 = east, counter-clockwise), speeds the forward
component of the velocity. Only a position keeps the telemetry fresh (``t_telemetry``):
ATTITUDE alone must not let a vehicle drive on a frozen position. The measurement time
is the vehicle's boot-clock stamp mapped onto the wall clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from openconvoy.bridge.link import Telemetry
from openconvoy.bridge.mavlink.ranging import RangeIntake
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.state import VehicleState, wrap_angle


class TelemetryIntake:
    """The vehicle's newest position, velocity, heading and their timing.

    Args:
        origin: the convoy origin (ENU frame).
        clock: monotonic link clock (s), stamps ``t_telemetry``.
        wall_clock: the shared clock (s) measurement times are mapped onto.
        on_reboot: called when the vehicle's clock went back (it rebooted).
    """

    def __init__(
        self,
        origin: Origin,
        clock: Callable[[], float],
        wall_clock: Callable[[], float],
        on_reboot: Callable[[], None],
    ) -> None:
        self.origin = origin
        self._clock = clock
        self._wall = wall_clock
        self._on_reboot = on_reboot
        self.pos: tuple[float, float, float, float] | None = None  # x, y, lat, lon
        self._vel_en: tuple[float, float] = (0.0, 0.0)
        self.heading: float | None = None
        self._yaw_rate = 0.0
        self._speed_prev: tuple[float, float] | None = None  # (vehicle time s, speed)
        self._accel = 0.0
        self._boot_offset: float | None = None  # wall clock - vehicle boot clock, s
        self._t_boot_offset = 0.0
        self._t_measured = math.nan  # wall-clock time of the newest measurement
        self.t_telemetry = -math.inf
        self.updated = False

    def on_position(self, msg: Any) -> None:
        """A GLOBAL_POSITION_INT: position, velocity, the heading until ATTITUDE gives one."""
        lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
        x, y, _ = geodetic_to_enu(self.origin, lat, lon)
        self.pos = (float(x), float(y), lat, lon)
        self._vel_en = (msg.vy * 0.01, msg.vx * 0.01)  # NED cm/s -> east, north m/s
        if self.heading is None and msg.hdg != 65535:
            self.heading = wrap_angle(math.pi / 2 - math.radians(msg.hdg * 0.01))
        self._update_speed(msg.time_boot_ms * 1e-3)
        self._mark_telemetry(msg.time_boot_ms * 1e-3)

    def on_attitude(self, msg: Any) -> None:
        """An ATTITUDE: heading and yaw rate."""
        self.heading = wrap_angle(math.pi / 2 - msg.yaw)  # NED yaw -> ENU heading
        self._yaw_rate = -msg.yawspeed  # clockwise-positive -> counter-clockwise
        # Fresher heading, but not fresher telemetry: only a position refreshes it.
        self.updated = True

    def _update_speed(self, t_vehicle: float) -> None:
        if self.heading is None:
            return
        speed = self._forward_speed()
        if self._speed_prev is not None:
            dt = t_vehicle - self._speed_prev[0]
            if dt > 1e-3:
                raw = (speed - self._speed_prev[1]) / dt
                self._accel = 0.5 * self._accel + 0.5 * raw  # light smoothing of a difference
        self._speed_prev = (t_vehicle, speed)

    def _forward_speed(self) -> float:
        h = self.heading or 0.0
        return self._vel_en[0] * math.cos(h) + self._vel_en[1] * math.sin(h)

    def _mark_telemetry(self, t_boot: float) -> None:
        self.t_telemetry = self._clock()
        self.updated = True
        # When was this measured, on the wall clock? A message can wait in the socket buffer
        # until the next poll, so the receive time overstates freshness. The smallest
        # (receive time - vehicle boot time) seen is the best estimate of the clock offset
        # (transport latency only); it may creep up 1 ms/s so vehicle clock drift and
        # reboots are followed.
        wall = self._wall()
        offset = wall - t_boot
        if self._boot_offset is not None and offset - self._boot_offset > 1.0:
            self._on_reboot()  # the vehicle clock went back: a reboot
        if self._boot_offset is not None:
            self._boot_offset += 1e-3 * max(0.0, wall - self._t_boot_offset)
        if (
            self._boot_offset is None
            or offset < self._boot_offset
            or offset - self._boot_offset > 1.0
        ):
            self._boot_offset = offset
        self._t_boot_offset = wall
        measured = t_boot + self._boot_offset
        # Position and attitude carry their own stamps; keep the state's time monotonic.
        self._t_measured = (
            measured if math.isnan(self._t_measured) else max(self._t_measured, measured)
        )

    def take(self) -> bool:
        """Whether new telemetry can be built (clears the flag when so)."""
        if self.updated and self.pos is not None and self.heading is not None:
            self.updated = False
            return True
        return False

    def build(
        self,
        vehicle: tuple[int, float, float],
        mode: str,
        armed: bool,
        t_heartbeat: float,
        ranging: RangeIntake,
    ) -> Telemetry:
        """The ``Telemetry`` of now, for ``vehicle`` = (vehicle id, length m, width m)."""
        assert self.pos is not None and self.heading is not None
        vehicle_id, length, width = vehicle
        x, y, lat, lon = self.pos
        state = VehicleState(
            vehicle_id=vehicle_id,
            t=self._t_measured,
            x=x,
            y=y,
            speed=self._forward_speed(),
            heading=self.heading,
            accel=self._accel,
            yaw_rate=self._yaw_rate,
            length=length,
            width=width,
        )
        return Telemetry(
            state=state,
            lat_deg=lat,
            lon_deg=lon,
            mode=mode,
            armed=armed,
            t_telemetry=self.t_telemetry,
            t_heartbeat=t_heartbeat,
            range_m=ranging.range_m,
            range_rate_mps=ranging.range_rate,
            t_range=ranging.t_range,
        )
