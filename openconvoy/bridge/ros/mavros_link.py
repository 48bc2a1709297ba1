"""``MavrosLink``: the vehicle link through MAVROS (ROS 1 now; any node with ``RosNode``'s
methods), for ArduPilot Rover and PX4, behind the same ``VehicleLink`` protocol as
``MavlinkLink``.

What it reads (MAVROS 1.x names under ``ns``, default ``/mavros``; the paper's code reads
the first four):

- ``global_position/global`` (NavSatFix): latitude, longitude → our ENU around the convoy
  origin (our geodesy, not MAVROS's map origin, which is wherever the first fix was);
  the header stamp (ROS time = the wall clock) is the state's time. It alone keeps the
  telemetry fresh (``t_telemetry``).
- ``global_position/compass_hdg`` (Float64, degrees clockwise from north) → ENU heading.
- ``global_position/local`` (Odometry): twist.linear is the ENU velocity (GLOBAL_POSITION_INT
  vy, vx: ``global_position.cpp``); speed = its component along the heading (negative when
  reversing).
- ``imu/data`` (Imu): angular_velocity.z (FLU, counter-clockwise) = the yaw rate.
- ``state`` (``mavros_msgs/State``): mode, armed, connected — for arming and the failsafes
  (the paper's code never read it); its arrival plays the heartbeat.

What it sends: MAVROS's ``setpoint_raw`` plugin (``setpoint_raw.cpp``), because it carries an
absolute yaw: ``setpoint_raw/global`` (GlobalPositionTarget → SET_POSITION_TARGET_GLOBAL_INT)
for ArduPilot (LOCAL_NED is ignored until its EKF has an origin) and ``setpoint_raw/local``
(PositionTarget → SET_POSITION_TARGET_LOCAL_NED) for PX4, type_mask 2503 (velocity + yaw),
with fields chosen so that after MAVROS's ENU→NED conversion (``ftf``) the MAVLink message
is exactly ``MavlinkLink``'s (``mavlink.setpoint.encode_setpoint``): ArduPilot takes the sign
of NED vx as the direction, so the body-forward speed must arrive in NED vx — that is ENU
**y** in the ROS message (velocity (0, speed, 0)), and the yaw is the ENU heading (MAVROS
sends π/2 − yaw); PX4 steers to the NED vector's bearing, so the ENU velocity is the
speed along the heading. The paper's ``setpoint_velocity/cmd_vel_unstamped`` (Twist) becomes
type_mask 1479 (velocity + yaw rate) in LOCAL_NED (``setpoint_velocity.cpp``): an ENU
velocity vector there reverses ArduPilot whenever it points south (docs/ros.md), and it
has no absolute heading; this link does not use it.

Modes and arming: ``set_mode`` (MAVROS sends SET_MODE and does not wait: the mode is
confirmed on ``state``), ``cmd/arming`` (MAVROS waits for the COMMAND_ACK: ``success``,
``result``). As ``MavlinkLink``: GUIDED/OFFBOARD first, arming retried while refused up to
the timeout, the mode checked again after arming (ArduPilot's RC switch), PX4 fed setpoints
before arming and its stream ended for good after a 1 s pause (``COM_OF_LOSS_T``). A mode
change away from GUIDED/OFFBOARD this link did not ask for latches ``pilot_took_over``; on
PX4 a change to POSCTL, AUTO.RTL or AUTO.LAND counts as its failsafe (``COM_OBL_RC_ACT``
and its RC/data-link loss actions; MAVROS 1.4's ``state`` carries no reason, and
``statustext/recv`` is not read).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from openconvoy.bridge.link import (
    Autopilot,
    CommandRefused,
    LinkLost,
    LinkTimeout,
    StatusCallback,
    Telemetry,
    VehicleLinkError,
)
from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.setpoint import PX4_RESUME_GAP_S, encode_setpoint
from openconvoy.bridge.ros import ftf
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.errors import LinkError
from openconvoy.core.state import VehicleState

GUIDED_MODE: dict[str, str] = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
HOLD_MODE: dict[str, str] = {"ardupilot": "HOLD", "px4": "AUTO.LOITER"}
PX4_FAILSAFE_MODES = ("POSCTL", "AUTO.RTL", "AUTO.LAND")
PX4_MODES = {"OFFBOARD", "POSCTL", "ALTCTL", "STABILIZED", "RATTITUDE"}
ARDUPILOT_ROVER_MODES = {"HOLD", "GUIDED", "STEERING", "SMART_RTL", "INITIALISING", "FOLLOW"}
PX4_PREARM_STREAM_S = 1.2
"""PX4 arms in OFFBOARD only after about 1 s of setpoints (AUTOPILOTS.md)."""


class RosNode(Protocol):
    """What the link needs of a ROS node (``bridge.ros.ros1.Ros1Node``)."""

    @property
    def alive(self) -> bool: ...

    def subscribe(
        self,
        topic: str,
        type_name: str,
        callback: Any,
        nodelay: bool = False,
        any_md5: bool = False,
    ) -> None: ...

    def advertise(self, topic: str, type_name: str, latch: bool = False) -> None: ...

    def publish(self, topic: str, msg: dict[str, Any]) -> None: ...

    def call(
        self, service: str, type_name: str, req: dict[str, Any], timeout_s: float = 5.0
    ) -> dict[str, Any]: ...

    def close(self) -> None: ...


def guess_autopilot(mode: str) -> Autopilot | None:
    """The firmware a MAVROS mode name betrays (None when it could be either, e.g. MANUAL)."""
    if mode.startswith("AUTO.") or mode in PX4_MODES:
        return "px4"
    if mode in ARDUPILOT_ROVER_MODES:
        return "ardupilot"
    return None


class MavrosLink:
    """Vehicle ``vehicle_id`` through the MAVROS node under ``ns``.

    Args:
        node_factory: makes (and starts) this link's ROS node; called by ``connect``.
        ns: MAVROS's namespace (``/mavros``, or per vehicle ``/vehicle_1/mavros``).
        origin: the convoy's ENU origin.
        autopilot: the firmware (None: told by the first mode name, see ``guess_autopilot``).
        clock: link clock (s, monotonic); wall: the shared clock (s).
    """

    FIRMWARE: Autopilot | None = None
    """The firmware when the interface itself says it (``ApDdsLink``: ArduPilot)."""

    def __init__(
        self,
        node_factory: Callable[[], RosNode],
        ns: str,
        origin: Origin,
        vehicle_id: int,
        autopilot: Autopilot | None = None,
        on_status: StatusCallback | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        telemetry_timeout_s: float = 0.5,
        heartbeat_timeout_s: float = 3.0,
        length_m: float = 0.0,
        width_m: float = 0.0,
    ) -> None:
        self.node_factory, self.ns, self.origin = node_factory, ns.rstrip("/"), origin
        self.vehicle_id, self.clock, self.wall = vehicle_id, clock, wall
        self.on_status = on_status or (lambda line: None)
        self.telemetry_timeout_s = telemetry_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.length_m, self.width_m = length_m, width_m
        self.telemetry_rates: dict[str, float] = {}
        self._autopilot: Autopilot | None = autopilot or self.FIRMWARE
        self.commands_sent = 0  # setpoints published
        self._node: RosNode | None = None
        self._lock = threading.Lock()
        self._reset_state()
        self.pilot_took_over = False
        self.takeover_reason = ""
        self.failsafe_took_over = False
        self._closed = True
        self._engaged: str | None = None  # the guided mode once we have it
        self._requested: str | None = None  # the mode we asked for last
        self._last_sp: tuple[float, float, float] | None = None  # speed, heading, clock
        self.stream_ended = ""
        self._reconnecting: threading.Thread | None = None
        self.setpoints = self  # one state behind all: its own ``Setpoints`` and ``Modes``
        self.modes = self

    def _reset_state(self) -> None:
        self._fix: tuple[float, float, float, float] | None = None  # lat, lon, stamp, clock
        self._fix_times: list[float] = []
        self._new_fix = False
        self._new_hdg = False
        self._hdg = math.nan
        self._vel = (0.0, 0.0)
        self._yaw_rate = 0.0
        self._mode, self._armed, self._connected = "", False, False
        self._t_state = -math.inf
        self._prev_speed: tuple[float, float] | None = None

    # ------------------------------------------------------------------ properties

    @property
    def autopilot(self) -> Autopilot:
        if self._autopilot is None:
            raise LinkLost("not connected: the autopilot is not known yet")
        return self._autopilot

    @property
    def lost(self) -> bool:
        node = self._node
        return self._closed or node is None or not node.alive or not self._connected

    # ------------------------------------------------------------------ callbacks

    def _t(self, name: str) -> str:
        return f"{self.ns}/{name}"

    def _on_state(self, m: dict[str, Any]) -> None:
        with self._lock:
            self._connected = bool(m.get("connected"))
            self._mode, self._armed = str(m.get("mode", "")), bool(m.get("armed"))
            if self._connected:
                self._t_state = self.clock()

    def _on_fix(self, m: dict[str, Any]) -> None:
        now = self.clock()
        stamp = float(m.get("header", {}).get("stamp", 0.0)) or self.wall()
        with self._lock:
            self._fix = (float(m["latitude"]), float(m["longitude"]), stamp, now)
            self._new_fix = True
            self._fix_times = (self._fix_times + [now])[-20:]

    def _on_hdg(self, m: dict[str, Any]) -> None:
        with self._lock:
            self._hdg = float(m.get("data", math.nan))
            self._new_hdg = True

    def _on_local(self, m: dict[str, Any]) -> None:
        lin = m.get("twist", {}).get("twist", {}).get("linear", {})
        with self._lock:
            self._vel = (float(lin.get("x", 0.0)), float(lin.get("y", 0.0)))

    def _on_imu(self, m: dict[str, Any]) -> None:
        with self._lock:
            self._yaw_rate = float(m.get("angular_velocity", {}).get("z", 0.0))

    # ------------------------------------------------------------------ connect

    def connect(self, timeout_s: float) -> None:
        """Start the node (once; a later call after a timeout keeps waiting on the same node
        and subscriptions) and wait for MAVROS's state, position and heading."""
        deadline = self.clock() + timeout_s
        if self._node is None or not self._node.alive:
            try:
                self._open()
            except LinkError as exc:  # the node could not start (no master, no rospy)
                raise LinkTimeout(f"MAVROS under {self.ns}: {exc}") from None
        self._closed = False
        while not (self._connected and self._fix is not None and math.isfinite(self._hdg)):
            if self.clock() > deadline:
                raise LinkTimeout(
                    f"no vehicle state and position from MAVROS under {self.ns} in {timeout_s:g} s"
                )
            time.sleep(0.02)
        if self._autopilot is None:
            self._autopilot = guess_autopilot(self._mode)
            if self._autopilot is None:
                self.close()
                raise VehicleLinkError(
                    f"cannot tell the autopilot from MAVROS's mode {self._mode!r}: give --autopilot"
                )
        # The rate the position arrives at (what the vehicle and MAVROS agreed to).
        t_end = self.clock() + 1.0
        while len(self._fix_times) < 5 and self.clock() < t_end:
            time.sleep(0.02)
        times = self._fix_times
        hz = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 1.0
        self.telemetry_rates = {"global_position/global": round(hz, 1)}

    def _open(self) -> None:
        self._reset_state()
        node = self.node_factory()
        t = self._t
        # TCP_NODELAY: small messages at 20 Hz must not wait on Nagle's algorithm.
        # State's MD5 changed in MAVROS 1.5 (constants only): take either (any_md5).
        node.subscribe(t("state"), "mavros_msgs/State", self._on_state, True, any_md5=True)
        node.subscribe(t("global_position/global"), "sensor_msgs/NavSatFix", self._on_fix, True)
        node.subscribe(t("global_position/compass_hdg"), "std_msgs/Float64", self._on_hdg, True)
        node.subscribe(t("global_position/local"), "nav_msgs/Odometry", self._on_local, True)
        node.subscribe(t("imu/data"), "sensor_msgs/Imu", self._on_imu, True)
        node.advertise(t("setpoint_raw/local"), "mavros_msgs/PositionTarget")
        node.advertise(t("setpoint_raw/global"), "mavros_msgs/GlobalPositionTarget")
        self._node, self._closed = node, False

    def reconnect(self, timeout_s: float) -> None:
        if self._node is not None:
            self._node.close()
            self._node = None
        if timeout_s > 0:
            self.connect(timeout_s)
            return

        def run() -> None:
            try:
                self.connect(30.0)
            except Exception:  # noqa: BLE001 - poll() keeps reporting the link lost
                pass

        self._closed = False
        self._reconnecting = threading.Thread(target=run, daemon=True)
        self._reconnecting.start()

    def close(self) -> None:
        self._closed = True
        if self._node is not None:
            self._node.close()
            self._node = None

    # ------------------------------------------------------------------ telemetry

    def poll(self) -> Telemetry | None:
        if self._closed or self._node is None:
            return None
        with self._lock:
            # One GLOBAL_POSITION_INT becomes three topics (global, local, compass_hdg) on
            # three connections: a state is new once its position and heading both are.
            fix, new = self._fix, self._new_fix and self._new_hdg
            if new:
                self._new_fix = self._new_hdg = False
            hdg_deg, (ve, vn), rate = self._hdg, self._vel, self._yaw_rate
            mode, armed, t_state = self._mode, self._armed, self._t_state
        self._watch_mode(mode)
        if fix is None or not new or not math.isfinite(hdg_deg):
            return None
        lat, lon, stamp, t_fix = fix
        x, y, _ = geodetic_to_enu(self.origin, lat, lon)
        heading = ftf.compass_hdg_to_enu_heading(hdg_deg)
        speed = ve * math.cos(heading) + vn * math.sin(heading)
        accel = 0.0
        if self._prev_speed is not None and stamp > self._prev_speed[1]:
            accel = (speed - self._prev_speed[0]) / (stamp - self._prev_speed[1])
        self._prev_speed = (speed, stamp)
        state = VehicleState(
            self.vehicle_id, stamp, float(x), float(y), speed, heading, accel, rate,
            self.length_m, self.width_m,
        )  # fmt: skip
        return Telemetry(state, lat, lon, mode, armed, t_fix, t_state)

    def _watch_mode(self, mode: str) -> None:
        """Latch a takeover: the guided mode left without this link asking."""
        if self._engaged is None or self.pilot_took_over or not mode:
            return
        if mode != self._engaged and mode != self._requested:
            self.pilot_took_over = True
            failsafe = self._autopilot == "px4" and mode in PX4_FAILSAFE_MODES
            self.failsafe_took_over = failsafe
            who = (
                "the autopilot's failsafe"
                if failsafe
                else "not this link (a pilot or the autopilot)"
            )
            self.takeover_reason = f"mode changed {self._engaged} -> {mode} by {who}"
            self.on_status(f"vehicle {self.vehicle_id}: {self.takeover_reason}")

    # ------------------------------------------------------------------ commands

    def _node_or_lost(self) -> RosNode:
        if self._node is None or self._closed:
            raise LinkLost("not connected")
        return self._node

    def _call(
        self, service: str, type_name: str, req: dict[str, Any], timeout_s: float = 5.0
    ) -> dict[str, Any]:
        """Call service ``ns/service``; no answer (or the node gone) is ``LinkTimeout``."""
        try:
            return self._node_or_lost().call(self._t(service), type_name, req, timeout_s)
        except (TimeoutError, OSError) as exc:
            raise LinkTimeout(f"{self._t(service)}: {exc}") from None

    def _set_mode(self, name: str) -> bool:
        self._requested = name
        r = self._call("set_mode", "mavros_msgs/SetMode", {"custom_mode": name})
        return bool(r.get("mode_sent"))

    def _wait(self, cond: Callable[[], bool], timeout_s: float, feed: bool = False) -> bool:
        deadline = self.clock() + timeout_s
        while not cond():
            if self.clock() > deadline:
                return False
            if feed:
                self._feed()
            time.sleep(0.05)
        return True

    def _feed(self) -> None:
        """PX4: a stop setpoint along the current heading (before and while arming)."""
        if self._autopilot == "px4":
            self._publish_setpoint(0.0, self._heading_now())

    def _heading_now(self) -> float:
        if math.isfinite(self._hdg):
            return ftf.compass_hdg_to_enu_heading(self._hdg)
        return self._last_sp[1] if self._last_sp else 0.0

    def _arm_call(self, value: bool, timeout_s: float = 5.0) -> dict[str, Any]:
        return self._call("cmd/arming", "mavros_msgs/CommandBool", {"value": value}, timeout_s)

    def prepare_and_arm(self, timeout_s: float, on_status: StatusCallback | None = None) -> None:
        say = on_status or self.on_status
        guided = GUIDED_MODE[self.autopilot]
        deadline = self.clock() + timeout_s
        if self.autopilot == "px4":
            self._wait(lambda: False, PX4_PREARM_STREAM_S, feed=True)
        result = "no answer"
        for attempt in range(1, 10_000):
            if self.clock() > deadline:
                break
            if self._mode != guided:
                self._set_mode(guided)
                if not self._wait(lambda: self._mode == guided, 2.0, feed=True):
                    say(f"vehicle {self.vehicle_id}: waiting for {guided} (mode {self._mode})")
                    continue
            r = self._arm_call(True)
            if r.get("success"):
                if not self._wait(lambda: self._armed, 2.0, feed=True):
                    continue
                # ArduPilot's RC mode switch may set MANUAL after arming: check again.
                self._wait(lambda: False, 0.6, feed=True)
                if self._mode == guided:
                    self._engaged, self._requested = guided, guided
                    self.stream_ended = ""
                    return
                say(
                    f"vehicle {self.vehicle_id}: mode {self._mode} after arming; asking {guided} again"
                )
                continue
            result = mp.result_name(int(r.get("result", mp.RESULT_FAILED)))
            say(
                f"vehicle {self.vehicle_id}: arming refused ({result}), retrying (attempt {attempt})"
            )
            self._wait(lambda: False, 1.0, feed=True)
        raise CommandRefused("MAV_CMD_COMPONENT_ARM_DISARM", result)

    def _publish_setpoint(self, speed_mps: float, heading_rad: float) -> None:
        node = self._node_or_lost()
        ap = self._autopilot or "ardupilot"
        sp = encode_setpoint(ap, speed_mps, heading_rad)
        # MAVROS turns ENU (e, n) into NED (n, e) and yaw into π/2 − yaw: invert both so the
        # MAVLink message carries encode_setpoint's NED fields.
        ve, vn, _ = ftf.transform_frame_ned_enu((sp.vx, sp.vy, 0.0))
        msg: dict[str, Any] = {
            "header": {"seq": 0, "stamp": self.wall(), "frame_id": ""},
            "type_mask": mp.TYPE_MASK_VEL_YAW,
            "velocity": {"x": ve, "y": vn, "z": 0.0},
            "yaw": float(heading_rad),
            "yaw_rate": 0.0,
        }
        if ap == "px4":
            msg["coordinate_frame"] = 1  # FRAME_LOCAL_NED
            node.publish(self._t("setpoint_raw/local"), msg)
        else:
            msg["coordinate_frame"] = 6  # FRAME_GLOBAL_REL_ALT
            node.publish(self._t("setpoint_raw/global"), msg)
        self._last_sp = (sp.speed, float(heading_rad), self.clock())
        self.commands_sent += 1

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        if self.pilot_took_over or self.lost or self.stream_ended:
            return False
        now = self.clock()
        if self._autopilot == "px4" and self._engaged and self._last_sp is not None:
            gap = now - self._last_sp[2]
            if gap > PX4_RESUME_GAP_S:
                self.stream_ended = (
                    f"the setpoint stream paused {gap:.2f} s (PX4's COM_OF_LOSS_T is 1 s)"
                )
                self.on_status(f"no more setpoints to this PX4: {self.stream_ended}")
                return False
        self._publish_setpoint(speed_mps, heading_rad)
        return True

    def stop(self) -> bool:
        return self.send(0.0, self._heading_now())

    def hold(self, timeout_s: float = 2.0) -> None:
        if self._node is None or self._closed:
            return
        name = HOLD_MODE[self.autopilot]
        self._engaged = None
        self._set_mode(name)
        if timeout_s > 0:
            self._wait(lambda: self._mode == name, timeout_s)

    def disarm(self, timeout_s: float = 2.0) -> None:
        if self._node is None or self._closed:
            return
        if timeout_s <= 0:
            threading.Thread(target=self._arm_call, args=(False,), daemon=True).start()
            return
        self._arm_call(False, timeout_s)
        self._wait(lambda: not self._armed, timeout_s)
