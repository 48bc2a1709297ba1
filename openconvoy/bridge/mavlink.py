"""``MavlinkLink``: the vehicle link over MAVLink (pymavlink), for ArduPilot Rover and PX4.

Follows shared/AUTOPILOTS.md and the firmware recordings in shared/sitl/ (ArduPilot Rover
4.7) and shared/sitl-px4/ (PX4 main, SIH Ackermann rover):

- connect by URL (``/dev/ttyUSB0`` with ``baud``, ``udp:``/``udpin:`` listen, ``udpout:``
  send, ``tcp:`` connect, ``tcpin:`` listen), wait for a vehicle heartbeat, identify the
  firmware (autopilot 3 = ArduPilot, 12 = PX4);
- telemetry is requested per message with ``MAV_CMD_SET_MESSAGE_INTERVAL`` at
  ``telemetry_hz`` (independent of the control rate); a refused rate is reported and
  retried lower. Only GLOBAL_POSITION_INT keeps the telemetry fresh (``link_ok``,
  ``Telemetry.t_telemetry``): ATTITUDE alone must not let a vehicle drive on a frozen
  position;
- a forward rangefinder (DISTANCE_SENSOR with orientation 0) gives range and range rate;
- arming: GUIDED / OFFBOARD (confirmed by the heartbeat), then arm, retrying while the
  autopilot refuses with its status text, bounded by a timeout; then the mode is checked
  again on a heartbeat received after arming (ArduPilot's RC mode switch sets MANUAL
  ~0.4 s after "ArduPilot Ready", and arming is accepted in MANUAL): a changed mode is
  requested again a bounded number of times, else the vehicle is disarmed and ``ModeLost``
  names the mode and who set it;
- every command's COMMAND_ACK is checked; a refusal raises ``CommandRefused`` with the
  autopilot's latest STATUSTEXT;
- a GCS heartbeat goes out at 1 Hz; lost links are detected (silence, missing heartbeat,
  TCP EOF — pymavlink reports that in a busy loop instead of raising); ``reconnect(0)``
  reopens in a helper thread and never blocks the caller;
- a mode change away from GUIDED/OFFBOARD that this link did not ask for latches
  ``pilot_took_over`` (``takeover_reason`` says by whom, as far as the link can tell).

Setpoints: what each firmware does with them (checked in its source and its recordings)
---------------------------------------------------------------------------------------

ArduPilot Rover, ``Rover/GCS_MAVLink_Rover.cpp`` (``handle_set_position_target_global_int``
and ``_local_ned``, unchanged since 2017): with the yaw or yaw-rate field in use, the sign of
``vx`` alone selects the direction ("we are using the x-axis velocity to determine
direction even though the frame is provided in MAV_FRAME_GLOBAL_xxx": ``if
(is_negative(packet.vx)) speed_dir = -1``), the speed is |(vx, vy)| and the nose points at
``yaw``. A NED vector with yaw therefore reverses on every heading with a southward
component (recorded: shared/sitl/ rows 6-8). So we send type_mask 2503, ``vx`` = the
body-forward speed, ``vy`` = 0, ``yaw`` absolute; only a negative commanded speed reverses.
Stop = speed 0 with yaw = the current heading (row 20: heading held within 0.5°), never the
zero velocity-only setpoint (row 21: "heading north", the nose swings ~80°). GLOBAL_INT is
used because LOCAL_NED is ignored until the EKF has an origin (rows 24-25).

PX4, ``src/modules/mavlink/mavlink_receiver.cpp`` (``handle_message_set_position_target_
local_ned`` / ``_global_int``): the message's velocity becomes ``trajectory_setpoint.velocity``
and ``offboard_control_mode.velocity``; the yaw is copied but the rover modules do not use it.
``src/modules/rover_ackermann/AckermannDriveModes/AckermannOffboardMode/AckermannOffboardMode.cpp``
(``offboardControl``): ``speed_body_x = |(vx, vy)|`` and ``yaw_setpoint = atan2f(vy, vx)``, so
the rover steers to the vector's bearing, never reverses, ignores the yaw field, and a zero
vector means bearing atan2(±0, ±0) = north or south by the sign of the zero (recorded:
shared/sitl-px4/ rows 7-9, 20-21: a ~48° swing from 2 m/s). ``rover_differential`` and
``rover_mecanum`` have their own offboard modes. So we keep the NED vector (speed along the
heading; type_mask 2503 with the yaw for firmwares that use it), and stop with a vanishing
vector along the current bearing (``_PX4_STOP_MPS`` = 0.001 m/s; recorded: stopped in
1.25 s from 2 m/s, heading 90.4 → 90.0°). PX4's commander leaves OFFBOARD
``COM_OF_LOSS_T`` (1 s) after the last setpoint and **returns to OFFBOARD by itself when
setpoints resume** (recorded, rows 16-18), so once the stream has paused that long, or the
autopilot link was lost, or a mode change we did not ask for was seen, this link sends no
setpoint again (``stream_ended``) until a new run.

Not thread-safe: one thread (the runner's loop) owns a link.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Literal

from openconvoy.bridge import mavproto as mp
from openconvoy.bridge.link import (
    Autopilot,
    CommandRefused,
    LinkLost,
    LinkTimeout,
    ModeLost,
    StatusCallback,
    Telemetry,
    VehicleLinkError,
)
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState, wrap_angle

log = logging.getLogger(__name__)

_URL_SCHEMES = ("udp:", "udpin:", "udpout:", "tcp:", "tcpin:")
_RATE_LADDER_HZ = (50.0, 40.0, 25.0, 20.0, 15.0, 10.0, 5.0, 4.0, 2.0, 1.0)
_TELEMETRY_MESSAGES = (mp.MSG_GLOBAL_POSITION_INT, mp.MSG_ATTITUDE)
_PX4_PRESTREAM_S = 1.2  # PX4 v1.16+ wants > 1 s of setpoints above 2 Hz before OFFBOARD
_KEEPALIVE_PERIOD_S = 0.1  # setpoint stream while blocking in PX4 preparation (10 Hz)
_MODE_CONFIRM_S = 2.5  # heartbeats come at 1 Hz: allow two and a half periods
_RETRY_PAUSE_S = 1.0
_MODE_REREQUESTS = 2  # a mode lost after arming is requested again this many times
_PX4_STOP_MPS = 0.001  # PX4's stop: a vanishing vector that still has a bearing (see above)
_PX4_RESUME_GAP_S = 1.0  # COM_OF_LOSS_T: after such a pause PX4 may be in its failsafe
_RANGE_WINDOW_S = 0.5  # range rate: least-squares slope over this much of the newest ranges
_RANGE_GAP_S = 0.5  # a range older than this (vehicle time) starts a new slope
_FAILSAFE_TEXT_S = 3.0  # a "failsafe" STATUSTEXT this recent explains a mode change


def check_url(url: str) -> str:
    """Validate a link URL; returns it. Raises ValueError naming what is wrong."""
    if url.startswith(_URL_SCHEMES):
        rest = url.split(":", 1)[1]
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ConfigError(
                f"MAVLink URL {url!r}: expected SCHEME:HOST:PORT with PORT in 1..65535, e.g. udpin:0.0.0.0:14550"
            )
        return url
    if url.startswith("/dev/") or url.upper().startswith("COM"):
        return url
    raise ConfigError(
        f"MAVLink URL {url!r}: expected a serial device (/dev/ttyX) or one of "
        f"{', '.join(s + 'HOST:PORT' for s in _URL_SCHEMES)}"
    )


class MavlinkLink:
    """A ``VehicleLink`` to one ArduPilot Rover or PX4 vehicle over pymavlink.

    Args:
        url: connection URL (see module docstring); serial devices use ``baud``.
        origin: convoy origin; positions are ENU metres around it.
        baud: serial baud rate (ignored for network URLs).
        vehicle_id: convoy position written into ``VehicleState.vehicle_id``.
        telemetry_hz: requested rate of GLOBAL_POSITION_INT and ATTITUDE, Hz.
        telemetry_timeout_s: ``link_ok`` is False after this long without telemetry, s.
        heartbeat_timeout_s: ``link_ok`` is False after this long without a heartbeat, s.
        length_m, width_m: vehicle size copied into the state (0 = unknown).
        setpoint_frame: ``"auto"`` (ArduPilot GLOBAL_INT, PX4 LOCAL_NED), ``"global"`` or
            ``"local"``.
        source_system, source_component: our MAVLink ids (default: a GCS-class system id
            and MAV_COMP_ID_ONBOARD_COMPUTER).
        clock: monotonic clock (s) for timeouts and freshness.
        wall_clock: clock (s) stamped into ``VehicleState.t`` (the shared, disciplined clock).
        on_status: receives status lines (refused rates, waiting for arming); default logs.
    """

    def __init__(
        self,
        url: str,
        origin: Origin,
        baud: int = 57600,
        *,
        vehicle_id: int = 0,
        telemetry_hz: float = 20.0,
        telemetry_timeout_s: float = 0.5,
        heartbeat_timeout_s: float = 3.0,
        length_m: float = 0.0,
        width_m: float = 0.0,
        setpoint_frame: Literal["auto", "global", "local"] = "auto",
        source_system: int = 255,
        source_component: int = 191,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        on_status: StatusCallback | None = None,
    ) -> None:
        self.url = check_url(url)
        if telemetry_hz <= 0:
            raise ConfigError(f"telemetry_hz must be positive, got {telemetry_hz}")
        self.origin = origin
        self.baud = baud
        self.vehicle_id = vehicle_id
        self.telemetry_hz = float(telemetry_hz)
        self.telemetry_timeout_s = telemetry_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.length_m = length_m
        self.width_m = width_m
        self.setpoint_frame = setpoint_frame
        self.source_system = source_system
        self.source_component = source_component
        self._clock = clock
        self._wall = wall_clock
        self._on_status = on_status or (lambda line: log.warning("%s", line))
        self._conn: Any = None
        self._pending: list[Any] = []  # a connection opened by the reconnect thread
        self._opener: threading.Thread | None = None
        self._reset_link_state()
        self._pilot_took_over = False
        self._takeover_reason = ""
        self._failsafe_took_over = False
        self._stream_ended = ""
        self._engaged_mode: str | None = None
        self._requested_mode: str | None = None
        self.telemetry_rates: dict[str, float] = {}
        """Accepted telemetry rate per message name, Hz (after ``connect``)."""
        self.last_setpoint: tuple[float, float, float] | None = None
        """(speed m/s, heading rad, link-clock time) of the newest setpoint sent."""
        self.last_refusal: CommandRefused | None = None
        """The newest refused command (also those sent without waiting, like ``hold(0)``)."""
        self.message_counts: dict[str, int] = {}
        """Messages received from the vehicle per type (for measuring achieved rates)."""

    # ----------------------------------------------------------------- connection

    def _reset_link_state(self) -> None:
        self._eof = False
        self._lost_reason = ""
        self._target: tuple[int, int] | None = None
        self._autopilot_id: int | None = None
        self._mode = "UNKNOWN"
        self._armed = False
        self._t_heartbeat = -math.inf
        self._t_telemetry = -math.inf
        self._t_gcs_heartbeat = -math.inf
        self._t_keepalive = -math.inf
        self._keepalive = False
        self._acks: dict[int, tuple[int, float]] = {}
        self._texts: deque[tuple[float, int, str]] = deque(maxlen=32)
        self._pos: tuple[float, float, float, float] | None = None  # x, y, lat, lon
        self._vel_en: tuple[float, float] = (0.0, 0.0)
        self._heading: float | None = None
        self._yaw_rate = 0.0
        self._speed_prev: tuple[float, float] | None = None  # (vehicle time s, speed)
        self._accel = 0.0
        self._boot_offset: float | None = None  # wall clock - vehicle boot clock, s
        self._t_boot_offset = 0.0
        self._t_measured = math.nan  # wall-clock time of the newest measurement
        self._updated = False
        self._telemetry: Telemetry | None = None
        self._heartbeats = 0
        self._ranges: deque[tuple[float, float]] = deque(maxlen=64)  # (vehicle time s, m)
        self._range_m = math.nan
        self._range_rate = math.nan
        self._t_range = -math.inf
        self._t0 = self._clock()

    def _open(self) -> None:
        self._install(self._make_connection())

    def _make_connection(self) -> Any:
        """A new pymavlink connection (may block: TCP connect); raises ``LinkLost``."""
        kwargs: dict[str, Any] = dict(
            source_system=self.source_system,
            source_component=self.source_component,
            autoreconnect=False,
        )
        if self.url.startswith("tcp:"):
            kwargs["retries"] = 1  # one attempt; reconnecting is the caller's decision
        try:
            conn = mp.mavutil.mavlink_connection(self.url, baud=self.baud, **kwargs)
        except OSError as exc:
            raise LinkLost(f"cannot open MAVLink link {self.url}: {exc}") from exc
        return conn

    def _install(self, conn: Any) -> None:
        # pymavlink's TCP link prints and "reconnects" (a no-op without autoreconnect) on EOF
        # and returns no data, forever: hook it so EOF marks the link lost instead.
        conn.handle_eof = lambda: self._mark_lost("connection closed by the vehicle (EOF)")
        conn.handle_disconnect = lambda: self._mark_lost("connection reset by the vehicle")
        self._conn = conn

    def _mark_lost(self, reason: str) -> None:
        if not self._eof:
            self._status(f"MAVLink link {self.url} lost: {reason}")
        self._eof = True
        self._lost_reason = reason

    def connect(self, timeout_s: float = 10.0) -> None:
        """Open the link, wait for a vehicle heartbeat, identify it and request telemetry.

        Raises ``LinkTimeout`` (no heartbeat within ``timeout_s`` s), ``LinkLost`` (cannot
        open), ``CommandRefused`` (no telemetry rate, down to 1 Hz, accepted)."""
        if self._conn is None:
            self._reset_link_state()
            self._open()
        if not self._wait_until(lambda: self._target is not None, timeout_s):
            raise LinkTimeout(
                f"no heartbeat from a vehicle on {self.url} within {timeout_s:g} s"
                + (f" ({self._lost_reason})" if self._eof else "")
            )
        self._request_telemetry()

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen a lost connection (``lost``: TCP EOF/reset, device error, or a failed
        reopen), wait for a heartbeat and re-request telemetry. A connection that is open
        but still waiting for its first heartbeat is kept, so repeated short calls add up.
        Raises like ``connect``. ``pilot_took_over`` stays latched.

        ``timeout_s`` <= 0 never blocks (what the runner's loop calls): the connection is
        opened in a helper thread (a TCP connect can take seconds) and installed by a later
        ``poll``; the telemetry intervals are re-sent without waiting for their ACKs when
        the first heartbeat arrives, so a vehicle that answers heartbeats but not commands
        cannot stall the caller. Open failures come as status lines."""
        if timeout_s > 0:
            if self.lost:
                self.close()
            self.connect(timeout_s)
            return
        if not self.lost or self._pending or (self._opener is not None and self._opener.is_alive()):
            return
        self.close()
        self._reset_link_state()

        def open_in_background() -> None:
            try:
                self._pending.append(self._make_connection())
            except LinkLost as exc:
                self._status(f"reconnect failed: {exc}")

        self._opener = threading.Thread(
            target=open_in_background, name="mavlink-reopen", daemon=True
        )
        self._opener.start()

    def _install_pending(self) -> None:
        if self._pending and self._conn is None:
            self._install(self._pending.pop())
            self._status(f"MAVLink link {self.url} reopened; waiting for the vehicle's heartbeat")

    def close(self) -> None:
        """Close the connection (idempotent)."""
        while self._pending:
            try:
                self._pending.pop().close()
            except OSError:
                pass
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None

    # ----------------------------------------------------------------- properties

    @property
    def autopilot(self) -> Autopilot:
        """``"ardupilot"`` or ``"px4"``; raises if no heartbeat identified the vehicle yet."""
        if self._autopilot_id == mp.AUTOPILOT_PX4:
            return "px4"
        if self._autopilot_id is None:
            raise LinkTimeout("vehicle not identified yet: call connect() first")
        return "ardupilot"

    @property
    def system_id(self) -> int | None:
        """The vehicle's MAVLink system id (None before its first heartbeat)."""
        return None if self._target is None else self._target[0]

    @property
    def mode(self) -> str:
        """The vehicle's mode name from its latest heartbeat (``"UNKNOWN"`` before one)."""
        return self._mode

    @property
    def armed(self) -> bool:
        """Armed bit of the latest heartbeat."""
        return self._armed

    @property
    def telemetry(self) -> Telemetry | None:
        """The newest telemetry (also when ``poll`` returned None this tick)."""
        return self._telemetry

    @property
    def pilot_took_over(self) -> bool:
        """Latched: the mode left GUIDED/OFFBOARD without this link asking (a person on
        the RC, a GCS, or PX4's offboard-loss failsafe)."""
        return self._pilot_took_over

    @property
    def takeover_reason(self) -> str:
        """One line: which mode the vehicle went to and who set it ("" before a takeover)."""
        return self._takeover_reason

    @property
    def failsafe_took_over(self) -> bool:
        """The takeover came with the autopilot's own failsafe text (not a person)."""
        return self._failsafe_took_over

    @property
    def stream_ended(self) -> str:
        """Why this link sends no more setpoints (PX4: a paused stream, a lost link or a
        takeover; "" while it may). Latched for the link's life: PX4 would re-enter
        OFFBOARD by itself if setpoints resumed after its failsafe."""
        return self._stream_ended

    @property
    def lost(self) -> bool:
        """No usable connection (TCP EOF/reset, device error, never opened or reopening
        failed): call ``reconnect``. A silent UDP link is not ``lost``: see ``link_ok``."""
        return self._eof or self._conn is None

    @property
    def status_texts(self) -> list[str]:
        """Recent STATUSTEXT lines from the autopilot, oldest first."""
        return [text for _, _, text in self._texts]

    def link_ok(self, now: float) -> bool:
        """True while open, telemetry younger than ``telemetry_timeout_s`` and the heartbeat
        younger than ``heartbeat_timeout_s`` at link-clock time ``now`` (s)."""
        return (
            self._conn is not None
            and not self._eof
            and now - self._t_telemetry <= self.telemetry_timeout_s
            and now - self._t_heartbeat <= self.heartbeat_timeout_s
        )

    # ----------------------------------------------------------------- receiving

    def poll(self) -> Telemetry | None:
        """Handle all pending messages and send the 1 Hz GCS heartbeat; non-blocking.

        Returns the new telemetry when a position or attitude message arrived since the
        last call (and a position is known), else None."""
        self._service()
        if self._updated and self._pos is not None and self._heading is not None:
            self._updated = False
            self._telemetry = self._build_telemetry()
            return self._telemetry
        return None

    def _service(self) -> None:
        """Periodic sends (GCS heartbeat, PX4 keep-alive stream) and draining."""
        self._install_pending()
        if self._conn is None:
            return
        now = self._clock()
        if now - self._t_gcs_heartbeat >= 1.0:
            self._t_gcs_heartbeat = now
            self._conn.mav.heartbeat_send(
                mp.MAV_TYPE_GCS, mp.mav().MAV_AUTOPILOT_INVALID, 0, 0, mp.mav().MAV_STATE_ACTIVE
            )
        if self._keepalive and now - self._t_keepalive >= _KEEPALIVE_PERIOD_S:
            self._t_keepalive = now
            self.stop_motion()
        self._drain()

    def _drain(self, max_messages: int = 5000) -> None:
        if self._eof:
            return  # a closed TCP link would report EOF on every read: stop reading
        for _ in range(max_messages):
            try:
                msg = self._conn.recv_msg()
            except OSError as exc:
                self._mark_lost(str(exc))
                return
            if msg is None or self._eof:
                return
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        src = msg.get_srcSystem()
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg)
            return
        if self._target is None or src != self._target[0]:
            return  # other systems (another GCS, other vehicles on a shared radio)
        self.message_counts[kind] = self.message_counts.get(kind, 0) + 1
        if kind == "GLOBAL_POSITION_INT":
            x, y, _ = geodetic_to_enu(self.origin, msg.lat * 1e-7, msg.lon * 1e-7)
            self._pos = (float(x), float(y), msg.lat * 1e-7, msg.lon * 1e-7)
            self._vel_en = (msg.vy * 0.01, msg.vx * 0.01)  # NED cm/s -> east, north m/s
            if self._heading is None and msg.hdg != 65535:
                self._heading = wrap_angle(math.pi / 2 - math.radians(msg.hdg * 0.01))
            self._update_speed(msg.time_boot_ms * 1e-3)
            self._mark_telemetry(msg.time_boot_ms * 1e-3)
        elif kind == "ATTITUDE":
            self._heading = wrap_angle(math.pi / 2 - msg.yaw)  # NED yaw -> ENU heading
            self._yaw_rate = -msg.yawspeed  # clockwise-positive -> counter-clockwise
            # Fresher heading, but not fresher telemetry: only a position refreshes it.
            self._updated = True
        elif kind == "DISTANCE_SENSOR":
            self._on_range(msg)
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            self._texts.append((self._clock(), msg.severity, text.rstrip("\x00")))
        elif kind == "COMMAND_ACK":
            if msg.result == mp.mav().MAV_RESULT_IN_PROGRESS:
                return
            self._acks[msg.command] = (msg.result, self._clock())
            if msg.result != mp.RESULT_ACCEPTED:
                self.last_refusal = CommandRefused(
                    mp.command_name(msg.command), mp.result_name(msg.result), self._reason()
                )

    def _on_heartbeat(self, msg: Any) -> None:
        m = mp.mav()
        # Only the autopilot's heartbeat counts: not GCSs, companions, gimbals, ADS-B
        # receivers or cameras (those report autopilot INVALID).
        if msg.type in (
            mp.MAV_TYPE_GCS,
            m.MAV_TYPE_ONBOARD_CONTROLLER,
            m.MAV_TYPE_GIMBAL,
            m.MAV_TYPE_ADSB,
        ):
            return
        if msg.autopilot == m.MAV_AUTOPILOT_INVALID:
            return
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if self._target is None:
            self._target = src
        elif src != self._target:
            return
        self.message_counts["HEARTBEAT"] = self.message_counts.get("HEARTBEAT", 0) + 1
        self._heartbeats += 1
        self._autopilot_id = msg.autopilot
        now = self._clock()
        if now - self._t_heartbeat > self.heartbeat_timeout_s and self.telemetry_rates:
            # The vehicle is back after silence (maybe rebooted, forgetting our intervals).
            self._rerequest_telemetry()
        self._t_heartbeat = now
        self._armed = bool(msg.base_mode & mp.mav().MAV_MODE_FLAG_SAFETY_ARMED)
        mode = mp.mode_name(msg.autopilot, msg.custom_mode)
        if (
            self._engaged_mode is not None
            and mode != self._engaged_mode
            and mode != self._requested_mode
            and not self._pilot_took_over
        ):
            self._pilot_took_over = True
            who = self._who_set_mode()
            self._failsafe_took_over = who.startswith("the autopilot's failsafe")
            self._takeover_reason = (
                f"mode changed from {self._engaged_mode} to {mode}, set by {who}"
            )
            self._end_stream("a mode change we did not ask for")
            self._status(f"{self._takeover_reason}: somebody else took over; no more setpoints")
        self._mode = mode

    def _who_set_mode(self) -> str:
        """Who changed the mode, as far as MAVLink tells: a recent failsafe STATUSTEXT
        names the autopilot itself; otherwise it was not this link."""
        now = self._clock()
        for t, _, text in reversed(self._texts):
            if now - t > _FAILSAFE_TEXT_S:
                break
            if "failsafe" in text.lower():
                return f"the autopilot's failsafe ({text.strip()!r})"
        if self._autopilot_id == mp.AUTOPILOT_PX4:
            return "not this link (the RC, another GCS, or a PX4 failsafe without a text)"
        return "not this link (the RC mode switch, MODE_CH, or another GCS)"

    def _end_stream(self, why: str) -> None:
        if not self._stream_ended and self._autopilot_id == mp.AUTOPILOT_PX4:
            self._stream_ended = why

    def _update_speed(self, t_vehicle: float) -> None:
        if self._heading is None:
            return
        speed = self._forward_speed()
        if self._speed_prev is not None:
            dt = t_vehicle - self._speed_prev[0]
            if dt > 1e-3:
                raw = (speed - self._speed_prev[1]) / dt
                self._accel = 0.5 * self._accel + 0.5 * raw  # light smoothing of a difference
        self._speed_prev = (t_vehicle, speed)

    def _forward_speed(self) -> float:
        h = self._heading or 0.0
        return self._vel_en[0] * math.cos(h) + self._vel_en[1] * math.sin(h)

    def _on_range(self, msg: Any) -> None:
        """A forward rangefinder (orientation 0 = MAV_SENSOR_ROTATION_NONE) reading: range
        (cm -> m) and its rate, the least-squares slope over the last ``_RANGE_WINDOW_S``
        of readings (1 cm steps at 10-20 Hz make a plain difference ±0.2 m/s of noise).
        Other orientations (PX4 SIH streams a downward one, orientation 25) are ignored;
        a reading outside [min_distance, max_distance) means nothing in range."""
        if msg.orientation != 0:
            return
        self._t_range = self._clock()
        cm = msg.current_distance
        if cm == 0xFFFF or cm < msg.min_distance or cm >= msg.max_distance or cm <= 0:
            self._ranges.clear()
            self._range_m = self._range_rate = math.nan
            return
        t = msg.time_boot_ms * 1e-3
        if self._ranges and not 0.0 < t - self._ranges[-1][0] <= _RANGE_GAP_S:
            self._ranges.clear()  # a gap, a repeat or a reboot: start a new slope
        self._ranges.append((t, cm * 0.01))
        while t - self._ranges[0][0] > _RANGE_WINDOW_S:
            self._ranges.popleft()
        self._range_m = cm * 0.01
        n = len(self._ranges)
        if n < 2:
            self._range_rate = math.nan
            return
        mt = sum(p[0] for p in self._ranges) / n
        mr = sum(p[1] for p in self._ranges) / n
        stt = sum((p[0] - mt) ** 2 for p in self._ranges)
        self._range_rate = sum((p[0] - mt) * (p[1] - mr) for p in self._ranges) / stt

    def _mark_telemetry(self, t_boot: float) -> None:
        self._t_telemetry = self._clock()
        self._updated = True
        # When was this measured, on the wall clock? A message can wait in the socket buffer
        # until the next poll, so the receive time overstates freshness. The smallest
        # (receive time - vehicle boot time) seen is the best estimate of the clock offset
        # (transport latency only); it may creep up 1 ms/s so vehicle clock drift and
        # reboots are followed.
        wall = self._wall()
        offset = wall - t_boot
        if (
            self._boot_offset is not None
            and offset - self._boot_offset > 1.0
            and self.telemetry_rates
        ):
            self._rerequest_telemetry()  # the vehicle clock went back: a reboot
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

    def _build_telemetry(self) -> Telemetry:
        assert self._pos is not None and self._heading is not None
        x, y, lat, lon = self._pos
        state = VehicleState(
            vehicle_id=self.vehicle_id,
            t=self._t_measured,
            x=x,
            y=y,
            speed=self._forward_speed(),
            heading=self._heading,
            accel=self._accel,
            yaw_rate=self._yaw_rate,
            length=self.length_m,
            width=self.width_m,
        )
        return Telemetry(
            state=state,
            lat_deg=lat,
            lon_deg=lon,
            mode=self._mode,
            armed=self._armed,
            t_telemetry=self._t_telemetry,
            t_heartbeat=self._t_heartbeat,
            range_m=self._range_m,
            range_rate_mps=self._range_rate,
            t_range=self._t_range,
        )

    # ----------------------------------------------------------------- commands

    def _status(self, line: str) -> None:
        self._on_status(line)

    def _reason(self, since: float = -math.inf) -> str:
        """The autopilot's newest status text received after ``since`` (link clock)."""
        if self._texts and self._texts[-1][0] >= since:
            return self._texts[-1][2]
        return ""

    def _wait_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        deadline = self._clock() + timeout_s
        while True:
            self._service()
            if predicate():
                return True
            if self._clock() >= deadline or self._conn is None:
                return False
            time.sleep(0.005)

    def _send_command(self, command: int, params: tuple[float, ...], confirmation: int = 0) -> None:
        assert self._target is not None
        p = tuple(params) + (0.0,) * (7 - len(params))
        self._conn.mav.command_long_send(
            self._target[0], self._target[1], command, confirmation, *p
        )

    def _command(
        self, command: int, params: tuple[float, ...], timeout_s: float = 1.5, tries: int = 3
    ) -> tuple[int, str]:
        """Send a COMMAND_LONG, retrying without an answer; (result, reason). Raises
        ``LinkTimeout`` without any COMMAND_ACK."""
        if self._target is None:
            raise LinkTimeout("vehicle not identified yet: call connect() first")
        t_sent = self._clock()
        for attempt in range(tries):
            self._acks.pop(command, None)
            self._send_command(command, params, confirmation=attempt)
            if self._wait_until(lambda: command in self._acks, timeout_s / tries):
                result = self._acks[command][0]
                reason = ""
                if result != mp.RESULT_ACCEPTED:
                    # The reason usually precedes the ACK; give a late one a moment.
                    self._wait_until(lambda: bool(self._reason(t_sent)), 0.1)
                    reason = self._reason(t_sent - 0.5)
                return result, reason
        raise LinkTimeout(
            f"no COMMAND_ACK for {mp.command_name(command)} within {timeout_s:g} s"
            + (f" ({self._lost_reason})" if self._eof else "")
        )

    def _request_telemetry(self) -> None:
        """SET_MESSAGE_INTERVAL per telemetry message, lowering refused rates."""
        rates: dict[str, float] = {}
        for msg_id in _TELEMETRY_MESSAGES:
            name = mp.message_name(msg_id)
            hz = self.telemetry_hz
            while True:
                result, reason = self._command(mp.CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz))
                if result == mp.RESULT_ACCEPTED:
                    rates[name] = hz
                    break
                lower = next((r for r in _RATE_LADDER_HZ if r < hz), None)
                why = f": {reason}" if reason else ""
                if lower is None:
                    raise CommandRefused(
                        f"MAV_CMD_SET_MESSAGE_INTERVAL({name} at {hz:g} Hz)",
                        mp.result_name(result),
                        reason,
                    )
                self._status(
                    f"{name} at {hz:g} Hz refused ({mp.result_name(result)}{why}); "
                    f"requesting {lower:g} Hz"
                )
                hz = lower
        self.telemetry_rates = rates

    def _rerequest_telemetry(self) -> None:
        """Send the accepted intervals again without waiting (from ``poll``); the answers
        are checked as they arrive (a refusal lands in ``last_refusal``)."""
        if self._target is None:
            return
        self._status("vehicle back after silence or a reboot: requesting telemetry again")
        for msg_id in _TELEMETRY_MESSAGES:
            hz = self.telemetry_rates.get(mp.message_name(msg_id))
            if hz:
                self._send_command(mp.CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / hz))

    def _guided_mode(self) -> str:
        return "OFFBOARD" if self.autopilot == "px4" else "GUIDED"

    def _hold_mode(self) -> str:
        return "LOITER" if self.autopilot == "px4" else "HOLD"

    def _mode_params(self, mode: str) -> tuple[float, ...]:
        flag = float(mp.mav().MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        if self.autopilot == "px4":
            main, sub = mp.PX4_MODE_NUMBERS[mode]
            return (flag, float(main), float(sub))
        return (flag, float(mp.ROVER_MODE_NUMBERS[mode]))

    def _set_mode(self, mode: str, deadline: float, on_status: StatusCallback) -> None:
        """Request ``mode`` until the heartbeat shows it; retry refusals until ``deadline``."""
        self._requested_mode = mode
        while True:
            result, reason = self._command(mp.CMD_DO_SET_MODE, self._mode_params(mode))
            if result == mp.RESULT_ACCEPTED:
                wait = max(0.0, min(_MODE_CONFIRM_S, deadline - self._clock()))
                if self._wait_until(lambda: self._mode == mode, wait):
                    return
                reason = reason or f"heartbeat still shows {self._mode}"
            left = deadline - self._clock()
            if left <= 0:
                raise CommandRefused(f"MAV_CMD_DO_SET_MODE({mode})", mp.result_name(result), reason)
            on_status(
                f"{mode} refused ({mp.result_name(result)}: {reason or 'no reason given'}); "
                f"retrying for {left:.0f} s more"
            )
            self._wait_until(lambda: False, min(_RETRY_PAUSE_S, left))

    def _arm(self, deadline: float, on_status: StatusCallback, mode: str | None = None) -> None:
        """Arm, waiting out the autopilot's refusals (estimator not ready) until ``deadline``.

        Before every attempt the mode must still be ``mode``: ArduPilot's init and RC mode
        switch replace a GUIDED set early in boot by MANUAL (shared/sitl rows 3-4), and it
        accepts arming in MANUAL ~19 s before GUIDED is armable (row 2)."""
        while True:
            if mode is not None and self._mode != mode:
                on_status(
                    f"mode is {self._mode} (set by {self._who_set_mode()}), not {mode}: "
                    f"requesting {mode} again before arming"
                )
                self._set_mode(mode, deadline, on_status)
            result, reason = self._command(mp.CMD_COMPONENT_ARM_DISARM, (1.0,))
            if result == mp.RESULT_ACCEPTED:
                wait = max(0.0, min(_MODE_CONFIRM_S, deadline - self._clock()))
                if self._wait_until(lambda: self._armed, wait):
                    return
                reason = reason or "heartbeat does not show armed"
            left = deadline - self._clock()
            if left <= 0:
                raise CommandRefused("MAV_CMD_COMPONENT_ARM_DISARM", mp.result_name(result), reason)
            on_status(
                f"waiting to arm: {mp.result_name(result)}: {reason or 'no reason given'}; "
                f"retrying for {left:.0f} s more"
            )
            self._wait_until(lambda: False, min(_RETRY_PAUSE_S, left))

    def prepare_and_arm(
        self, timeout_s: float = 60.0, on_status: StatusCallback | None = None
    ) -> None:
        """Switch to GUIDED (ArduPilot) or OFFBOARD (PX4) and arm, standing still; then
        check the mode again on a heartbeat received after arming.

        PX4: streams stop setpoints (10 Hz) for 1.2 s first and during the whole call; from
        its return on, the caller must keep sending setpoints above 2 Hz. Refusals are
        retried with status lines (``on_status``) until ``timeout_s`` s have passed; then
        ``CommandRefused`` names the command and the autopilot's reason. A mode lost after
        arming (ArduPilot's RC mode switch at boot) is requested again up to
        ``_MODE_REREQUESTS`` times; if it still does not hold, the vehicle is disarmed and
        ``ModeLost`` says which mode it is in and who set it. Not allowed once a pilot
        took over."""
        if self._pilot_took_over:
            raise CommandRefused(
                "prepare_and_arm", "PILOT_TOOK_OVER", "a pilot took over this vehicle"
            )
        status = on_status or self._status
        deadline = self._clock() + timeout_s
        target = self._guided_mode()
        self._engaged_mode = None
        if self.autopilot == "px4":
            self._keepalive = True
            try:
                self._wait_until(lambda: False, _PX4_PRESTREAM_S)
                self._set_mode(target, deadline, status)
                self._arm(deadline, status, target)
                self._keep_mode_after_arming(target, status)
            finally:
                self._keepalive = False
        else:
            self._set_mode(target, deadline, status)
            self._arm(deadline, status, target)
            self._keep_mode_after_arming(target, status)
        self._engaged_mode = target
        self._requested_mode = target

    def _next_heartbeat(self) -> bool:
        """Wait for a heartbeat received after now (at most ``_MODE_CONFIRM_S``)."""
        n = self._heartbeats
        return self._wait_until(lambda: self._heartbeats > n, _MODE_CONFIRM_S)

    def _keep_mode_after_arming(self, target: str, status: StatusCallback) -> None:
        """The mode on a heartbeat after arming must still be ``target``; else ask again
        (bounded), else disarm and raise ``ModeLost``."""
        for attempt in range(_MODE_REREQUESTS + 1):
            if not self._next_heartbeat():
                raise LinkTimeout(f"no heartbeat within {_MODE_CONFIRM_S:g} s after arming")
            if self._mode == target and self._armed:
                return
            if not self._armed:
                raise ModeLost(
                    f"vehicle disarmed right after arming (mode {self._mode}, "
                    f"set by {self._who_set_mode()})"
                )
            who = self._who_set_mode()
            if attempt == _MODE_REREQUESTS:
                break
            status(
                f"mode changed to {self._mode} after arming, set by {who}; "
                f"requesting {target} again ({attempt + 1} of {_MODE_REREQUESTS})"
            )
            try:
                self._set_mode(target, self._clock() + _MODE_CONFIRM_S, status)
            except CommandRefused as exc:
                status(f"{target} refused again: {exc}")
        mode = self._mode
        try:
            self.disarm(2.0)
            after = "disarmed"
        except VehicleLinkError as exc:
            after = f"DISARM FAILED ({exc}): the vehicle may still be armed"
        raise ModeLost(
            f"vehicle armed in {mode}, not {target}: set by {who}; {target} requested "
            f"{_MODE_REREQUESTS} more times and not kept; {after}. Check the RC mode switch "
            f"({'MODE_CH' if self.autopilot == 'ardupilot' else 'COM_RC_IN_MODE'}) and INITIAL_MODE"
        )

    def _setpoint_frame(self) -> str:
        if self.setpoint_frame != "auto":
            return self.setpoint_frame
        return "local" if self.autopilot == "px4" else "global"

    def _may_send(self, now: float) -> bool:
        """Whether a setpoint may go out now; latches ``stream_ended`` on PX4 once the
        stream paused longer than ``COM_OF_LOSS_T`` or the autopilot link was lost while
        engaged (PX4 would be in its failsafe and would take OFFBOARD back on the next
        setpoint: a run must not resume driving a vehicle whose failsafe took it)."""
        if (
            self._conn is None
            or self._target is None
            or self._pilot_took_over
            or self._stream_ended
        ):
            return False
        if self.autopilot == "px4" and self._engaged_mode is not None:
            gap = now - self.last_setpoint[2] if self.last_setpoint is not None else 0.0
            if gap > _PX4_RESUME_GAP_S:
                self._end_stream(
                    f"the setpoint stream paused {gap:.2f} s (PX4's COM_OF_LOSS_T is 1 s)"
                )
            elif not self.link_ok(now):
                self._end_stream("the autopilot link was lost")
            if self._stream_ended:
                self._status(f"no more setpoints to this PX4: {self._stream_ended}")
                return False
        return True

    def send_setpoint(self, speed_mps: float, heading_rad: float) -> bool:
        """Send speed (m/s, forward) and ENU heading (rad); one MAVLink message, no waiting.

        ArduPilot: type_mask 2503, vx = the speed along the body axis (negative = reverse),
        vy = 0, yaw absolute. PX4: the NED vector of the speed along the heading (PX4
        rovers cannot reverse: a negative speed is sent as a stop), never shorter than
        ``_PX4_STOP_MPS`` so that it keeps a bearing. See the module docstring. Returns
        False without sending when there is no link, a pilot took over, or the PX4 stream
        ended (``stream_ended``)."""
        now = self._clock()
        if not self._may_send(now):
            return False
        speed = float(speed_mps)
        if not math.isfinite(speed):
            speed = 0.0
        yaw = wrap_angle(math.pi / 2 - float(heading_rad))  # ENU heading -> NED yaw
        if self.autopilot == "px4":
            along = max(speed, _PX4_STOP_MPS)
            vx, vy = along * math.cos(yaw), along * math.sin(yaw)
            speed = max(speed, 0.0)
        else:
            vx, vy = speed + 0.0, 0.0  # + 0.0 turns a -0.0 into +0.0: only v < 0 reverses
        t_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        ts, tc = self._target
        if self._setpoint_frame() == "global":
            self._conn.mav.set_position_target_global_int_send(
                t_ms,
                ts,
                tc,
                mp.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                mp.TYPE_MASK_VEL_YAW,
                0,
                0,
                0.0,
                vx,
                vy,
                0.0,
                0.0,
                0.0,
                0.0,
                yaw,
                0.0,
            )
        else:
            self._conn.mav.set_position_target_local_ned_send(
                t_ms,
                ts,
                tc,
                mp.MAV_FRAME_LOCAL_NED,
                mp.TYPE_MASK_VEL_YAW,
                0.0,
                0.0,
                0.0,
                vx,
                vy,
                0.0,
                0.0,
                0.0,
                0.0,
                yaw,
                0.0,
            )
        self.last_setpoint = (speed, float(heading_rad), now)
        return True

    def stop_motion(self) -> bool:
        """Speed 0 along the current heading (the last commanded one before telemetry):
        ArduPilot vx = 0 with yaw = heading; PX4 a 0.001 m/s vector along it.

        Never the zero velocity vector, which both firmwares read as "bearing north"."""
        heading = self._heading
        if heading is None:
            heading = self.last_setpoint[1] if self.last_setpoint else 0.0
        return self.send_setpoint(0.0, heading)

    def hold(self, timeout_s: float = 2.0) -> None:
        """Switch to HOLD (ArduPilot) or AUTO.LOITER (PX4). A requested hold is not a
        takeover. ``timeout_s`` > 0 waits for the heartbeat to confirm (raising
        ``CommandRefused``); 0 sends and returns (a refusal lands in ``last_refusal``).
        Stop first: PX4's Hold loops back to where it engaged (recorded: 150 °/s turns
        from 2 m/s), ArduPilot's coasts without braking."""
        mode = self._hold_mode()
        self._engaged_mode = None
        self._requested_mode = mode
        if timeout_s <= 0:
            if self._conn is not None and self._target is not None:
                self._send_command(mp.CMD_DO_SET_MODE, self._mode_params(mode))
            return
        self._set_mode(mode, self._clock() + timeout_s, self._status)

    def set_mode(self, mode: str, timeout_s: float = 3.0) -> None:
        """Request a mode by name (``"GUIDED"``, ``"HOLD"``, ``"MANUAL"``; PX4 ``"OFFBOARD"``,
        ``"LOITER"``, ...) until the heartbeat confirms it; refusals are retried until
        ``timeout_s`` s, then ``CommandRefused``. Entering the guided mode this way does not
        arm, and does not clear ``pilot_took_over``."""
        known = mp.PX4_MODE_NUMBERS if self.autopilot == "px4" else mp.ROVER_MODE_NUMBERS
        if mode not in known:
            raise ValueError(f"unknown {self.autopilot} mode {mode!r}; one of {', '.join(known)}")
        self._engaged_mode = None
        self._set_mode(mode, self._clock() + timeout_s, self._status)

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Disarm (standing still); raises ``CommandRefused`` if refused. ``timeout_s`` 0
        sends and returns."""
        if timeout_s <= 0:
            if self._conn is not None and self._target is not None:
                self._send_command(mp.CMD_COMPONENT_ARM_DISARM, (0.0,))
            return
        result, reason = self._command(mp.CMD_COMPONENT_ARM_DISARM, (0.0,), timeout_s)
        if result != mp.RESULT_ACCEPTED:
            raise CommandRefused(
                "MAV_CMD_COMPONENT_ARM_DISARM(disarm)", mp.result_name(result), reason
            )
