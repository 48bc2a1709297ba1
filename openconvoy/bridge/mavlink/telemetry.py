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

REBOOT_JUMP_S = 1.0
"""A (receive time - boot time) this much above the envelope: the vehicle's clock went back."""

BUCKET_S = 1.0
"""The envelope keeps the least offset of each bucket this long (s, wall clock)."""

BUCKETS = 10
"""How many buckets (the newest included) the envelope and its drift are taken from."""

MAX_DRIFT = 0.05
"""The largest clock drift followed (s/s): a vehicle clock 5 % off is a broken one."""


class BootClockOffset:
    """Wall clock - vehicle boot clock (s), followed through the vehicle clock's drift.

    Each received stamp gives ``wall - t_boot`` = the offset + its transport and polling
    latency (>= 0), so the offset is the lower envelope of those: the least of each
    ``BUCKET_S`` bucket, the last ``BUCKETS`` of them, with the drift their line shows,
    projected to now. A clock that runs slow (PX4 SIH at 0.990 of real time,
    shared/sitl-px4 README row 24) moves the offset 10 ms/s; followed at a fixed creep of
    1 ms/s instead, the mapped state fell 9 ms/s behind and read 0.59 s old after a minute.
    """

    def __init__(self) -> None:
        self._mins: list[tuple[float, float]] = []  # (wall time s, least offset s) per bucket
        self._bucket = -math.inf

    def observe(self, wall: float, t_boot: float) -> bool:
        """Take one stamp (wall clock s, vehicle boot clock s); True when the vehicle's clock
        went back (a reboot: the envelope starts again)."""
        offset = wall - t_boot
        if self._mins and offset - self.offset(wall) > REBOOT_JUMP_S:
            self._mins.clear()
            self._bucket = -math.inf
            rebooted = True
        else:
            rebooted = False
        bucket = math.floor(wall / BUCKET_S)
        if bucket != self._bucket:
            self._bucket = bucket
            self._mins.append((wall, offset))
            del self._mins[:-BUCKETS]
        elif offset < self._mins[-1][1]:
            self._mins[-1] = (wall, offset)
        return rebooted

    def drift(self) -> float:
        """The offset's growth (s/s): the least-squares line through the buckets' least
        offsets (0 with fewer than 3 buckets), within +-``MAX_DRIFT``."""
        n = len(self._mins)
        if n < 3:
            return 0.0
        tm = sum(t for t, _ in self._mins) / n
        om = sum(o for _, o in self._mins) / n
        var = sum((t - tm) ** 2 for t, _ in self._mins)
        if var <= 0.0:
            return 0.0
        slope = sum((t - tm) * (o - om) for t, o in self._mins) / var
        return max(-MAX_DRIFT, min(MAX_DRIFT, slope))

    def offset(self, wall: float) -> float:
        """The offset (s) at wall-clock time ``wall``: the envelope's lowest bucket least
        brought to ``wall`` at the drift; NaN before any stamp."""
        if not self._mins:
            return math.nan
        d = self.drift()
        return min(o + d * (wall - t) for t, o in self._mins)


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
        self._offset = BootClockOffset()
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
        # until the next poll, so the receive time overstates freshness: the vehicle's clock
        # is mapped by the lower envelope of (receive time - boot time), drift included.
        wall = self._wall()
        if self._offset.observe(wall, t_boot):
            self._on_reboot()  # the vehicle clock went back: a reboot
        measured = t_boot + self._offset.offset(wall)
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
