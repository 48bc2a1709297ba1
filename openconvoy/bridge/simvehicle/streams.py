"""What a simulated autopilot sends (``simvehicle.SimVehicle``): heartbeats and telemetry
streams at their requested intervals, on the firmware's loop ticks, and STATUSTEXTs.

Streams run on the firmware's 50 Hz scheduler, so 20 Hz comes as alternating 40/60 ms
intervals, all messages of one rate in one burst (as ArduPilot's). Rates are set by
SET_MESSAGE_INTERVAL, within the firmware's rules (``max_message_hz``, or the firmware
model's own refusal).
"""

from __future__ import annotations

import math
import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.ardupilot import ArduPilotRover
from openconvoy.bridge.simvehicle.motion import MotionState
from openconvoy.bridge.simvehicle.px4 import Px4Rover
from openconvoy.bridge.simvehicle.world import SimWorld, distance_sensor_cm
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.envs.vehicles import RangingSensor

if TYPE_CHECKING:
    from openconvoy.bridge.simvehicle.vehicle import SimVehicleConfig

MSG_HEARTBEAT = 0
MSG_RC_CHANNELS = 65
MSG_SERVO_OUTPUT_RAW = 36
MSG_DISTANCE_SENSOR = 132
RANGE_HZ = 20.0
"""DISTANCE_SENSOR rate (Hz): a lidar at ArduPilot's usual 20 Hz stream rate."""
MAV_DISTANCE_SENSOR_LASER = 0
STREAMS = (
    mp.MSG_GLOBAL_POSITION_INT,
    mp.MSG_ATTITUDE,
    mp.MSG_VFR_HUD,
    mp.MSG_LOCAL_POSITION_NED,
    MSG_SERVO_OUTPUT_RAW,
    MSG_RC_CHANNELS,
)
"""The telemetry streams a simulated vehicle has (its rate set per message)."""
_TEXT_CHUNK = 50


class _GeodeticCache:
    """ENU -> geodetic through a linear map re-anchored (with pymap3d) every ``span_m``:
    within 25 m of an anchor the map's error is below 0.1 mm, and it costs a few µs
    instead of pymap3d's ~1.5 ms per GLOBAL_POSITION_INT."""

    def __init__(self, home: Origin, span_m: float = 25.0) -> None:
        self.home = home
        self.span_m = span_m
        self._anchor: tuple[float, float] | None = None
        self._map = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def _reanchor(self, east: float, north: float) -> None:
        lat0, lon0, alt0 = enu_to_geodetic(self.home, east, north, 0.0)
        lat_e, lon_e, _ = enu_to_geodetic(self.home, east + 1.0, north, 0.0)
        lat_n, lon_n, _ = enu_to_geodetic(self.home, east, north + 1.0, 0.0)
        self._anchor = (east, north)
        self._map = (lat0, lon0, alt0, lat_e - lat0, lat_n - lat0, lon_e - lon0, lon_n - lon0)

    def __call__(self, east: float, north: float) -> tuple[float, float, float]:
        a = self._anchor
        if a is None or abs(east - a[0]) > self.span_m or abs(north - a[1]) > self.span_m:
            self._reanchor(east, north)
            a = (east, north)
        lat0, lon0, alt0, dlat_e, dlat_n, dlon_e, dlon_n = self._map
        de, dn = east - a[0], north - a[1]
        return lat0 + dlat_e * de + dlat_n * dn, lon0 + dlon_e * de + dlon_n * dn, alt0


class SimStreams:
    """The heartbeat, telemetry and text sender of one simulated vehicle.

    Args:
        config: the vehicle's config (default rate, rate limit, GPS noise, home, id).
        firmware: the firmware model (heartbeat contents, servo outputs, timing).
        motion: the vehicle's motion state, read under ``lock``.
        lock: guards ``motion`` against the vehicle's loop thread.
        rng: the noise source (GPS noise, range noise).
        ranging: the forward rangefinder and the world it measures (None: none).

    Attributes:
        intervals: message id -> interval (s; 0 = disabled).
        due: message id -> vehicle time (s) it is next due.
    """

    def __init__(
        self,
        config: SimVehicleConfig,
        firmware: ArduPilotRover | Px4Rover,
        motion: MotionState,
        lock: threading.Lock,
        rng: np.random.Generator,
        ranging: tuple[RangingSensor, SimWorld] | None,
    ) -> None:
        self._config = config
        self._fw = firmware
        self._motion = motion
        self._lock = lock
        self._rng = rng
        self._ranging = ranging
        default_iv = 1.0 / config.default_message_hz
        self.intervals: dict[int, float] = {m: default_iv for m in STREAMS}
        self.intervals[MSG_HEARTBEAT] = 1.0
        if ranging is not None:
            self.intervals[MSG_DISTANCE_SENSOR] = 1.0 / RANGE_HZ
        self.due: dict[int, float] = {}
        self._geodetic = _GeodeticCache(config.home)
        self._text_id = 0
        self._other_owed = 0.0  # other onboard messages due but not yet sent
        self._t_other = 0.0

    def rates_hz(self) -> dict[str, float]:
        """Current telemetry rate per message name (0 = disabled)."""
        return {
            mp.message_name(m): (0.0 if iv <= 0 else 1.0 / iv) for m, iv in self.intervals.items()
        }

    def set_interval(self, t: float, msg_id: int, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL at vehicle time ``t`` (s): the MAV_RESULT. A negative
        interval disables the stream, 0 restores its default."""
        if msg_id not in self.intervals:
            return mp.RESULT_FAILED
        if interval_us < 0:
            self.intervals[msg_id] = 0.0  # disabled
        elif interval_us == 0:
            self.intervals[msg_id] = (
                1.0 if msg_id == MSG_HEARTBEAT else 1.0 / self._config.default_message_hz
            )
        else:
            hz = 1e6 / interval_us
            limit = self._config.max_message_hz
            if limit is not None and hz > limit + 1e-9:
                self._fw.texts.append(
                    (
                        6,
                        f"Requested rate for message ID {msg_id} too fast. Increase SCHED_LOOP_RATE",
                    )
                )
                return mp.RESULT_DENIED
            result = self._fw.interval(msg_id, hz)
            if result != mp.RESULT_ACCEPTED:
                return result  # the previous rate is kept
            self.intervals[msg_id] = interval_us * 1e-6
        iv = self.intervals[msg_id]
        # On a grid from boot: streams at one rate go out in the same burst, as ArduPilot's.
        self.due[msg_id] = math.ceil(t / iv + 1e-9) * iv if iv > 0 else 0.0
        return mp.RESULT_ACCEPTED

    def send_due(self, mav: Any, t: float) -> None:
        """Streams on the loop's ticks: a message goes out on the first tick within half a
        tick of its due time, so 20 Hz on a 50 Hz loop alternates 40 and 60 ms."""
        half = 0.5 * self._fw.loop_dt
        if self._fw.heartbeat_now:
            self._fw.heartbeat_now = False
            self.heartbeat(mav, t)
        for msg_id, interval in self.intervals.items():
            if interval <= 0:
                continue
            due = self.due.get(msg_id, t)
            if t + half < due:
                continue
            self.due[msg_id] = due + interval if t - due < interval else t + interval
            if msg_id == MSG_HEARTBEAT:
                self.heartbeat(mav, t)
            else:
                self.send_telemetry(mav, msg_id, t)
        self._send_other(mav, t)

    def _send_other(self, mav: Any, t: float) -> None:
        """The firmware's other onboard streams, ``config.other_streams_hz`` messages/s in
        all (TIMESYNC here; a real PX4 sends ~200/s of TIMESYNC, ALTITUDE, VFR_HUD,
        GPS_RAW_INT, SYS_STATUS, ... at their default rates, shared/sitl-px4/README.md)."""
        rate = self._config.other_streams_hz
        if rate <= 0:
            return
        self._other_owed += rate * max(0.0, t - self._t_other)
        self._t_other = t
        ns = int(t * 1e9)
        while self._other_owed >= 1.0:
            self._other_owed -= 1.0
            mav.timesync_send(0, ns)

    def heartbeat(self, mav: Any, t: float) -> None:
        base, custom, status = self._fw.heartbeat(t)
        mav.heartbeat_send(mp.MAV_TYPE_GROUND_ROVER, self._fw.autopilot_id, base, custom, status)

    def send_telemetry(self, mav: Any, msg_id: int, t: float) -> bool:
        fw = self._fw
        with self._lock:
            s = self._motion
            north, east, yaw, v, yaw_rate = s.north, s.east, s.yaw, s.speed, s.yaw_rate
            # The velocity is the true one (GPS); the heading is the estimator's.
            vn, ve = v * math.cos(yaw), v * math.sin(yaw)
            yaw = s.estimated_yaw
        t_ms = int(t * fw.clock_ratio * 1000) & 0xFFFFFFFF
        if msg_id == mp.MSG_GLOBAL_POSITION_INT:
            if self._config.gps_noise_m > 0:
                north += float(self._rng.normal(0.0, self._config.gps_noise_m))
                east += float(self._rng.normal(0.0, self._config.gps_noise_m))
            lat, lon, alt = self._geodetic(east, north)
            mav.global_position_int_send(
                t_ms,
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round(alt * 1000)),
                0,
                int(round(vn * 100)),
                int(round(ve * 100)),
                0,
                int(round(math.degrees(yaw) * 100)) % 36000,
            )
        elif msg_id == mp.MSG_ATTITUDE:
            mav.attitude_send(t_ms, 0.0, 0.0, yaw, 0.0, 0.0, yaw_rate)
        elif msg_id == mp.MSG_VFR_HUD:
            thr = fw.servo_pwm()[1]
            mav.vfr_hud_send(
                abs(v),
                abs(v),
                int(round(math.degrees(yaw))) % 360,
                int(max(0, (thr - 1500) / 5)),
                0.0,
                0.0,
            )
        elif msg_id == mp.MSG_LOCAL_POSITION_NED:
            if not fw.position_flowing(t):
                return False
            mav.local_position_ned_send(t_ms, north, east, 0.0, vn, ve, 0.0)
        elif msg_id == MSG_SERVO_OUTPUT_RAW:
            steer, thr = fw.servo_pwm()
            mav.servo_output_raw_send(
                int(t * fw.clock_ratio * 1e6) & 0xFFFFFFFF, 0, steer, 1500, thr, 1500, 0, 0, 0, 0
            )
        elif msg_id == MSG_DISTANCE_SENSOR:
            self._send_range(mav, t_ms)
        elif msg_id == MSG_RC_CHANNELS:
            ch = fw.rc_channels()
            mav.rc_channels_send(t_ms, 8 if ch[0] else 0, *ch, *([0] * 10), 255)
        return True

    def _send_range(self, mav: Any, t_ms: int) -> None:
        """DISTANCE_SENSOR from the world's true geometry plus the sensor's noise."""
        if self._ranging is None:
            return
        sensor, world = self._ranging
        reading = world.forward_range(self._config.system_id, sensor.max_range_m)
        lo, hi, cm = distance_sensor_cm(
            reading, sensor.max_range_m, sensor.range_noise_m, lambda: float(self._rng.normal())
        )
        mav.distance_sensor_send(t_ms, lo, hi, cm, MAV_DISTANCE_SENSOR_LASER, 0, 0, 0)

    def text(self, mav: Any, severity: int, text: str) -> None:
        """STATUSTEXT, split into 50-byte chunks with an id as ArduPilot and PX4 do."""
        data = text.encode()
        if len(data) <= _TEXT_CHUNK:
            mav.statustext_send(severity, data, 0, 0)
            return
        self._text_id = self._text_id % 0xFFFF + 1
        for seq, i in enumerate(range(0, len(data), _TEXT_CHUNK)):
            mav.statustext_send(severity, data[i : i + _TEXT_CHUNK], self._text_id, seq)
