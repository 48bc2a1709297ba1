"""``Px4DdsLink``: a ``VehicleLink`` that drives a PX4 vehicle through PX4's own DDS topics
(uXRCE-DDS, ``/fmu/in/*`` and ``/fmu/out/*``), Cyclone DDS directly, no ROS install.

What it sends, as PX4's offboard guide and ``dds_topics.yaml`` (PX4 main) ask:
``/fmu/in/offboard_control_mode`` (``velocity`` true) with every setpoint — the runner
ticks at 20-50 Hz, far above PX4's 2 Hz minimum, and the signal dies with the controller,
so PX4's offboard-loss failsafe (COM_OF_LOSS_T) catches a hung runner; a background
heartbeat would keep a dead controller's last setpoint alive. ``/fmu/in/trajectory_setpoint``:
the velocity vector in NED (north = speed·sin(heading_enu), east = speed·cos(heading_enu))
and ``yaw`` the NED heading (π/2 − ENU heading), position NaN (not controlled). PX4 rovers
steer to the velocity vector's bearing and never reverse, so a speed is sent as a
direction, never negative and never shorter than MavlinkLink's ``PX4_STOP_MPS`` (a
zero vector has no bearing: the rover would turn north). Arm and mode through ``/fmu/in/vehicle_command``
(COMPONENT_ARM_DISARM 400, DO_SET_MODE 176 with PX4's main/sub mode in param2/param3),
answered on ``/fmu/out/vehicle_command_ack``. State from ``/fmu/out/vehicle_status``
(the heartbeat: arming_state, nav_state, failsafe), ``vehicle_global_position`` (the
position, mapped to ENU around the convoy origin) and ``vehicle_local_position`` (NED
velocity and heading).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from openconvoy.bridge.link import (
    Autopilot,
    CommandRefused,
    LinkLost,
    LinkTimeout,
    StatusCallback,
    Telemetry,
)
from openconvoy.bridge.mavlink.setpoint import PX4_STOP_MPS
from openconvoy.bridge.px4dds import msgs
from openconvoy.bridge.px4dds.dds import IN_QOS, OUT_READER_QOS, Participant, take_all, topic_name
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState

MODE_NAMES = {
    msgs.NAVIGATION_STATE_MANUAL: "MANUAL",
    msgs.NAVIGATION_STATE_POSCTL: "POSCTL",
    msgs.NAVIGATION_STATE_AUTO_LOITER: "HOLD",
    msgs.NAVIGATION_STATE_OFFBOARD: "OFFBOARD",
}
"""nav_state -> the mode name in ``Telemetry.mode`` (AUTO_LOITER is PX4's rover Hold)."""

PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER, PX4_MAIN_OFFBOARD = 4, 3, 6
"""PX4's custom main/sub modes (``px4_custom_mode.h``) for DO_SET_MODE's param2/param3."""


def ned_velocity(speed_mps: float, heading_enu_rad: float) -> tuple[float, float]:
    """Forward speed (m/s) along an ENU heading (rad, 0 = east, CCW) -> NED (north, east) m/s."""
    return speed_mps * math.sin(heading_enu_rad), speed_mps * math.cos(heading_enu_rad)


def ned_yaw(heading_enu_rad: float) -> float:
    """ENU heading (0 = east, CCW) -> NED yaw (0 = north, CW), wrapped to (-π, π]."""
    return math.remainder(math.pi / 2 - heading_enu_rad, math.tau)


class Px4DdsLink:
    """Vehicle ``vehicle_id`` behind PX4 namespace ``ns`` (``UXRCE_DDS_NS``, e.g.
    ``"vehicle_1"``; "" = none) on DDS ``domain_id``; positions in ENU around ``origin``.
    ``localhost`` keeps DDS on the loopback interface (tests, demos); ``iface`` on that
    network interface (``--dds-iface``)."""

    telemetry_timeout_s = 0.5
    heartbeat_timeout_s = 3.0  # vehicle_status comes at 1 Hz (each HEARTBEAT) to 5 Hz

    def __init__(
        self,
        ns: str,
        origin: Origin,
        vehicle_id: int,
        domain_id: int = 0,
        localhost: bool = False,
        on_status: StatusCallback | None = None,
        clock: Callable[[], float] = time.monotonic,
        iface: str | None = None,
    ) -> None:
        self.ns, self.origin, self.vehicle_id = ns, origin, vehicle_id
        if localhost and iface:
            raise ConfigError("--dds-localhost and --dds-iface: choose one")
        self.domain_id, self.localhost, self.iface = domain_id, localhost, iface
        self.on_status = on_status or (lambda line: None)
        self.clock = clock
        self.telemetry_rates: dict[str, float] = {}
        self.dropped: dict[str, int] = {}
        self._part: Participant | None = None
        self.setpoints = self  # one state behind all: its own ``Setpoints`` and ``Modes``
        self.modes = self
        self._reset_state()

    def _reset_state(self) -> None:
        self._status: msgs.VehicleStatus | None = None
        self._lpos: msgs.VehicleLocalPosition | None = None
        self._acks: list[msgs.VehicleCommandAck] = []
        self._t_heartbeat = -math.inf
        self._t_telemetry = -math.inf
        self._last: Telemetry | None = None
        self._returned: Telemetry | None = None  # the last one ``poll`` handed out
        self._commanding = False
        self._took_over = False
        self._reason = ""
        self._failsafe = False
        self._asked_mode: int | None = None

    # ------------------------------------------------------------------ properties

    @property
    def autopilot(self) -> Autopilot:
        """Always ``"px4"``: only PX4 speaks these topics."""
        return "px4"

    @property
    def pilot_took_over(self) -> bool:
        """Latched once nav_state left OFFBOARD without this link asking."""
        return self._took_over

    @property
    def takeover_reason(self) -> str:
        """Which mode the vehicle went to and why ("" before a takeover)."""
        return self._reason

    @property
    def failsafe_took_over(self) -> bool:
        """The takeover came with vehicle_status.failsafe set (PX4's own failsafe)."""
        return self._failsafe

    @property
    def lost(self) -> bool:
        """No DDS participant (closed, or never connected)."""
        return self._part is None

    # ------------------------------------------------------------------ connection

    def _open(self) -> None:
        p = self._part = Participant(self.domain_id, self.localhost, self.iface)
        n = self.ns
        self._w_ocm = p.writer(topic_name(n, "in", msgs.OffboardControlMode), msgs.OffboardControlMode, IN_QOS)  # fmt: skip
        self._w_sp = p.writer(topic_name(n, "in", msgs.TrajectorySetpoint), msgs.TrajectorySetpoint, IN_QOS)  # fmt: skip
        self._w_cmd = p.writer(
            topic_name(n, "in", msgs.VehicleCommand), msgs.VehicleCommand, IN_QOS
        )
        self._r_status = p.reader(topic_name(n, "out", msgs.VehicleStatus), msgs.VehicleStatus, OUT_READER_QOS)  # fmt: skip
        self._r_gpos = p.reader(topic_name(n, "out", msgs.VehicleGlobalPosition), msgs.VehicleGlobalPosition, OUT_READER_QOS)  # fmt: skip
        self._r_lpos = p.reader(topic_name(n, "out", msgs.VehicleLocalPosition), msgs.VehicleLocalPosition, OUT_READER_QOS)  # fmt: skip
        self._r_ack = p.reader(topic_name(n, "out", msgs.VehicleCommandAck), msgs.VehicleCommandAck, OUT_READER_QOS)  # fmt: skip

    def connect(self, timeout_s: float) -> None:
        """Join the DDS domain and wait for a vehicle_status (``LinkTimeout`` if none)."""
        if self._part is None:
            self._open()
        if not self._wait(lambda: self._status is not None, timeout_s):
            raise LinkTimeout(
                f"no {topic_name(self.ns, 'out', msgs.VehicleStatus)} in {timeout_s:.1f} s"
            )
        # dds_topics.yaml's rate limits (Hz) of the topics read
        self.telemetry_rates = {
            "vehicle_status": 5.0,
            "vehicle_global_position": 50.0,
            "vehicle_local_position": 50.0,
        }

    def reconnect(self, timeout_s: float) -> None:
        """Leave and rejoin the domain; 0 = do not wait for vehicle_status."""
        self.close()
        self._reset_state()
        self._open()
        if timeout_s > 0:
            self.connect(timeout_s)

    def close(self) -> None:
        """Leave the DDS domain (idempotent)."""
        if self._part is not None:
            self._part.close()
            self._part = None

    # ------------------------------------------------------------------ reading

    def poll(self) -> Telemetry | None:
        """Take every pending sample; the telemetry not yet returned by ``poll`` (a new
        global position, also one taken while ``prepare_and_arm`` waited) or None."""
        self._pump()
        if self._last is None or self._last is self._returned:
            return None
        self._returned = self._last
        return self._last

    def _pump(self) -> None:
        """Take every pending sample (the internal waits read through this, so that what
        they take still reaches the caller's next ``poll``)."""
        if self._part is None:
            return
        now = self.clock()
        for st in take_all(self._r_status, self.dropped, "vehicle_status", msgs.VehicleStatus):
            self._on_status(st, now)
        for lp in take_all(
            self._r_lpos, self.dropped, "vehicle_local_position", msgs.VehicleLocalPosition
        ):
            if _finite(lp.vx, lp.vy, lp.heading):
                self._lpos = lp
            else:
                self.dropped["vehicle_local_position"] = self.dropped.get("vehicle_local_position", 0) + 1  # fmt: skip
        self._acks.extend(
            take_all(self._r_ack, self.dropped, "vehicle_command_ack", msgs.VehicleCommandAck)
        )
        for gp in take_all(
            self._r_gpos, self.dropped, "vehicle_global_position", msgs.VehicleGlobalPosition
        ):
            if not (
                gp.lat_lon_valid
                and _finite(gp.lat, gp.lon)
                and abs(gp.lat) <= 90
                and abs(gp.lon) <= 180
            ):
                self.dropped["vehicle_global_position"] = self.dropped.get("vehicle_global_position", 0) + 1  # fmt: skip
                continue
            self._telemetry(gp, now)

    def _on_status(self, st: msgs.VehicleStatus, now: float) -> None:
        self._status, self._t_heartbeat = st, now
        if (
            self._commanding
            and not self._took_over
            and st.nav_state != msgs.NAVIGATION_STATE_OFFBOARD
            and st.nav_state != self._asked_mode
        ):
            self._took_over, self._failsafe = True, bool(st.failsafe)
            who = "PX4's failsafe" if st.failsafe else "not this link (a pilot or GCS)"
            name = MODE_NAMES.get(st.nav_state, f"nav_state {st.nav_state}")
            self._reason = f"vehicle went to {name}, set by {who}"

    def _telemetry(self, gp: msgs.VehicleGlobalPosition, now: float) -> Telemetry:
        x, y, _ = geodetic_to_enu(self.origin, gp.lat, gp.lon, self.origin.alt_m)
        lp, prev = self._lpos, self._last
        heading = math.pi / 2 - lp.heading if lp is not None else 0.0
        heading = math.remainder(heading, math.tau)
        # forward speed: the NED velocity along the heading (negative when rolling back)
        speed = 0.0 if lp is None else lp.vx * math.sin(heading) + lp.vy * math.cos(heading)
        wall = time.time()
        accel = yaw_rate = 0.0
        if prev is not None and wall - prev.state.t > 1e-3:
            dt = wall - prev.state.t
            accel = (speed - prev.state.speed) / dt
            yaw_rate = math.remainder(heading - prev.state.heading, math.tau) / dt
        st = self._status
        self._t_telemetry = now
        self._last = Telemetry(
            state=VehicleState(
                vehicle_id=self.vehicle_id, t=wall, x=float(x), y=float(y), speed=speed,
                heading=heading, accel=accel, yaw_rate=yaw_rate,
            ),
            lat_deg=gp.lat, lon_deg=gp.lon,
            mode=MODE_NAMES.get(st.nav_state, f"NAV{st.nav_state}") if st else "",
            armed=bool(st and st.arming_state == msgs.ARMING_STATE_ARMED),
            t_telemetry=now, t_heartbeat=self._t_heartbeat,
        )  # fmt: skip
        return self._last

    # ------------------------------------------------------------------ commands

    def _require(self) -> None:
        if self._part is None:
            raise LinkLost("px4-dds link is closed")

    def _command(self, command: int, *params: float) -> None:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self._w_cmd.write(
            msgs.VehicleCommand(
                timestamp=_us(), param1=p[0], param2=p[1], param3=p[2], param4=p[3],
                param5=p[4], param6=p[5], param7=p[6], command=command, target_system=1,
                target_component=1, source_system=1, source_component=191, from_external=True,
            )
        )  # fmt: skip

    def _command_ack(self, command: int, timeout_s: float, *params: float) -> int | None:
        """Send a vehicle_command and wait for its ack's result (None: no ack in time)."""
        self._acks.clear()
        self._command(command, *params)
        got: list[int] = []

        def acked() -> bool:
            got.extend(a.result for a in self._acks if a.command == command)
            self._acks.clear()
            return bool(got)

        return got[0] if self._wait(acked, timeout_s) else None

    def _stream(self, speed_mps: float, heading_rad: float) -> None:
        self._w_ocm.write(msgs.OffboardControlMode(timestamp=_us(), velocity=True))
        vn, ve = ned_velocity(max(PX4_STOP_MPS, speed_mps), heading_rad)
        nan = math.nan
        self._w_sp.write(
            msgs.TrajectorySetpoint(
                timestamp=_us(), position=[nan, nan, nan], velocity=[vn, ve, nan],
                yaw=ned_yaw(heading_rad),
            )
        )  # fmt: skip

    def _heading_now(self) -> float:
        return self._last.state.heading if self._last is not None else 0.0

    def prepare_and_arm(self, timeout_s: float, on_status: StatusCallback | None = None) -> None:
        """Stream a standing-still setpoint, switch to OFFBOARD and arm; retries while PX4
        refuses (``CommandRefused`` with its result after ``timeout_s``)."""
        self._require()
        say = on_status or self.on_status
        end = self.clock() + timeout_s
        self._asked_mode = msgs.NAVIGATION_STATE_OFFBOARD
        self._stream_for(0.5)  # PX4 takes OFFBOARD only with the signal alive
        result: int | None = None
        while self.clock() < end:
            self._stream(0.0, self._heading_now())
            mode = self._command_ack(msgs.VEHICLE_CMD_DO_SET_MODE, 0.5, 1.0, PX4_MAIN_OFFBOARD, 0.0)
            self._stream(0.0, self._heading_now())
            result = self._command_ack(msgs.VEHICLE_CMD_COMPONENT_ARM_DISARM, 0.5, 1.0)
            if (
                mode == msgs.VEHICLE_CMD_RESULT_ACCEPTED
                and result == msgs.VEHICLE_CMD_RESULT_ACCEPTED
            ):
                if self._wait_streaming(lambda: self._armed_offboard(), 2.0):
                    self._commanding = True
                    return
            say(
                f"vehicle {self.vehicle_id}: PX4 refused arming/offboard (result {result}), retrying"
            )
            self._stream_for(0.5)
        raise CommandRefused("VEHICLE_CMD_COMPONENT_ARM_DISARM", f"VEHICLE_CMD_RESULT {result}")

    def _armed_offboard(self) -> bool:
        st = self._status
        return bool(
            st and st.arming_state == msgs.ARMING_STATE_ARMED
            and st.nav_state == msgs.NAVIGATION_STATE_OFFBOARD
        )  # fmt: skip

    def _stream_for(self, seconds: float) -> None:
        self._wait_streaming(lambda: False, seconds)

    def _wait_streaming(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        """Like ``_wait`` but keeps the offboard signal alive (20 Hz) meanwhile."""
        end = self.clock() + timeout_s
        while True:
            self._stream(0.0, self._heading_now())
            self._pump()
            if cond():
                return True
            if self.clock() >= end:
                return False
            time.sleep(0.05)

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Offboard signal + NED velocity setpoint; False once a pilot took over."""
        if self._took_over or self._part is None:
            return False
        self._stream(speed_mps, heading_rad)
        return True

    def stop(self) -> bool:
        """Speed 0 along the current heading (never a zero velocity in a stale direction)."""
        return self.send(0.0, self._heading_now())

    def hold(self, timeout_s: float = 2.0) -> None:
        """Stop, then AUTO.LOITER (PX4's rover Hold); 0 = do not wait."""
        self._require()
        self.stop()
        self._asked_mode = msgs.NAVIGATION_STATE_AUTO_LOITER
        self._command(msgs.VEHICLE_CMD_DO_SET_MODE, 1.0, PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER)
        if timeout_s > 0:
            self._wait(
                lambda: bool(self._status and self._status.nav_state == msgs.NAVIGATION_STATE_AUTO_LOITER),
                timeout_s,
            )  # fmt: skip
        self._commanding = False

    def disarm(self, timeout_s: float = 2.0) -> None:
        """COMPONENT_ARM_DISARM 0; 0 = send and do not wait."""
        self._require()
        self._command(msgs.VEHICLE_CMD_COMPONENT_ARM_DISARM, 0.0)
        if timeout_s > 0:
            self._wait(
                lambda: bool(self._status and self._status.arming_state == msgs.ARMING_STATE_DISARMED),
                timeout_s,
            )  # fmt: skip

    def _wait(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        end = self.clock() + timeout_s
        while True:
            self._pump()
            if cond():
                return True
            if self.clock() >= end:
                return False
            time.sleep(0.01)


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


def _us() -> int:
    return int(time.monotonic() * 1e6)
