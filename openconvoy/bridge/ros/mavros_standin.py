"""A stand-in for MAVROS: the ROS side of a vehicle, forwarding to an autopilot over MAVLink.

MAVROS is not packaged anywhere our CI can reach, so tests and the ROS demo run this node in
its place, in front of our simulated ArduPilot/PX4 (``bridge.simvehicle``, real MAVLink over
UDP). It offers the names and does the conversions of MAVROS **1.4.0** (github.com/mavlink/
mavros, tag 1.4.0; the ROS 1 ``master`` branch to 1.21.0 does the same for everything here),
plugin by plugin:

- ``sys_status.cpp``: ``~state`` (``mavros_msgs/State``) on every HEARTBEAT (connected,
  armed = base_mode & 128, guided = base_mode & 8, manual_input = base_mode & 64, mode =
  ``str_mode_v10``'s name from ``uas_stringify.cpp``'s rover/PX4 maps, system_status), and
  ``connected = false`` after ``conn/timeout`` (10 s) without one; ``~set_mode``
  (``SetMode``): the mode name back to custom_mode (``cmode_from_str``), base_mode |=
  SAFETY_ARMED if armed | CUSTOM_MODE_ENABLED, sent as MAVLink SET_MODE (#11) without
  waiting for an answer (``mode_sent`` = the name was known); a GCS HEARTBEAT at 1 Hz
  (``conn/heartbeat_rate``; type ONBOARD_CONTROLLER, autopilot INVALID).
- ``command.cpp``: ``~cmd/arming`` (``CommandBool``) = COMMAND_LONG
  COMPONENT_ARM_DISARM (param1 1/0), waiting for its COMMAND_ACK (``success`` = ACCEPTED,
  ``result`` = the MAV_RESULT; no ACK in time: the call fails).
- ``global_position.cpp`` (GLOBAL_POSITION_INT): ``~global_position/global`` (NavSatFix:
  lat, lon, alt; no GPS_RAW_INT here, so status NO_FIX, covariance unknown),
  ``~global_position/local`` (Odometry: ENU position from the map origin — the first fix;
  twist.linear = (vy, vx, vz)/100, i.e. ENU east, north and MAVLink's vz unchanged),
  ``~global_position/compass_hdg`` (Float64, hdg/100 degrees, NaN for UINT16_MAX),
  ``~global_position/rel_alt``.
- ``imu.cpp`` (ATTITUDE): ``~imu/data`` orientation ENU/FLU
  (``ftf.attitude_ned_to_enu``), angular_velocity FLU = (rollspeed, −pitchspeed, −yawspeed).
- ``setpoint_raw.cpp``: ``~setpoint_raw/local`` (PositionTarget) →
  SET_POSITION_TARGET_LOCAL_NED and ``~setpoint_raw/global`` (GlobalPositionTarget) →
  SET_POSITION_TARGET_GLOBAL_INT, velocity ENU→NED, yaw by ``ftf.setpoint_yaw_enu_to_ned``,
  yaw rate negated, frame and type_mask passed through.
- ``setpoint_velocity.cpp``: ``~setpoint_velocity/cmd_vel_unstamped`` (Twist) →
  SET_POSITION_TARGET_LOCAL_NED, frame LOCAL_NED (the ``mav_frame`` default), type_mask
  1479 (``(1 << 10) | (7 << 6) | (7 << 0)``: velocity + yaw rate), velocity ENU→NED, yaw
  rate = −angular.z. The paper's code drives through this topic; what ArduPilot Rover does
  with it is in docs/ros.md (the sign of NED vx picks the direction).

Not modelled: the other plugins, parameters, mission, time sync, the AMSL↔ellipsoid altitude
conversion (we carry the altitude unchanged), ``GPS_RAW_INT``. Stream rates: real MAVROS
relies on the autopilot's stream settings (ArduPilot SRx_ parameters, PX4's MAVLink
profile) or its ``set_message_interval`` service; this node asks for GLOBAL_POSITION_INT and
ATTITUDE at ``rate_hz`` with MAV_CMD_SET_MESSAGE_INTERVAL once it hears the vehicle.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.companion import CompanionMavlink, run_threads, stop_threads
from openconvoy.bridge.ros import ftf

ROVER_CMODES: dict[int, str] = {
    0: "MANUAL",
    1: "ACRO",
    3: "STEERING",
    4: "HOLD",
    5: "LOITER",
    6: "FOLLOW",
    7: "SIMPLE",
    10: "AUTO",
    11: "RTL",
    12: "SMART_RTL",
    15: "GUIDED",
    16: "INITIALISING",
}
"""``uas_stringify.cpp``'s ``apmrover2_cmode_map`` (MAVROS 1.4.0)."""

PX4_CMODES: dict[tuple[int, int], str] = {
    (1, 0): "MANUAL",
    (5, 0): "ACRO",
    (2, 0): "ALTCTL",
    (3, 0): "POSCTL",
    (6, 0): "OFFBOARD",
    (7, 0): "STABILIZED",
    (8, 0): "RATTITUDE",
    (4, 4): "AUTO.MISSION",
    (4, 3): "AUTO.LOITER",
    (4, 5): "AUTO.RTL",
    (4, 6): "AUTO.LAND",
    (4, 7): "AUTO.RTGS",
    (4, 1): "AUTO.READY",
    (4, 2): "AUTO.TAKEOFF",
}
"""``uas_stringify.cpp``'s ``px4_cmode_map``: (main mode, sub mode) -> name."""

CONN_TIMEOUT_S = 10.0
"""MAVROS's ``conn/timeout`` default: ``connected`` drops after this long without a heartbeat."""

TYPE_MASK_CMD_VEL = (1 << 10) | (7 << 6) | (7 << 0)
"""``setpoint_velocity.cpp``'s ``ignore_all_except_v_xyz_yr`` = 1479."""


def mode_name(autopilot: int, custom_mode: int) -> str:
    """``UAS::str_mode_v10`` for a custom mode (``CMODE(n)`` when unknown)."""
    if autopilot == mp.AUTOPILOT_PX4:
        key = ((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
        name = PX4_CMODES.get(key) or PX4_CMODES.get((key[0], 0))
    else:
        name = ROVER_CMODES.get(custom_mode)
    return name if name is not None else f"CMODE({custom_mode})"


def custom_mode_of(autopilot: int, name: str) -> int | None:
    """``UAS::cmode_from_str``: a mode name (or a number) back to custom_mode; None if unknown."""
    name = name.upper()
    if autopilot == mp.AUTOPILOT_PX4:
        for (main, sub), n in PX4_CMODES.items():
            if n == name:
                return (main << 16) | (sub << 24)
    else:
        for num, n in ROVER_CMODES.items():
            if n == name:
                return num
    try:
        return int(name)
    except ValueError:
        return None


class MavrosStandIn:
    """The stand-in node: ROS side ``node`` (a ``Ros1Node``) under namespace ``ns`` (e.g.
    ``/vehicle_1/mavros``), MAVLink side ``mavlink_url`` (pymavlink URL, e.g.
    ``udpout:127.0.0.1:14551``). ``start`` begins; ``stop`` ends (idempotent)."""

    def __init__(
        self,
        node: Any,
        mavlink_url: str,
        ns: str = "/mavros",
        rate_hz: float = 20.0,
        conn_timeout_s: float = CONN_TIMEOUT_S,
    ):
        self.node, self.ns, self.rate_hz = node, ns.rstrip("/"), rate_hz
        self.conn_timeout_s = conn_timeout_s  # MAVROS's ``conn/timeout`` parameter
        # MAVROS's defaults: system_id 1, component_id 240 (MAV_COMP_ID_UDP_BRIDGE).
        self.mavlink = CompanionMavlink(mavlink_url, 240)
        self._stop = threading.Event()
        self._acks: dict[int, tuple[threading.Event, list[int]]] = {}
        self.tgt_system = 0
        self.autopilot = -1
        self.base_mode = 0
        self.t_heartbeat = -math.inf
        self.connected = False
        self.map_origin: tuple[float, float, float] | None = None
        self.setpoints_forwarded = 0
        self._threads: list[threading.Thread] = []

    def _t(self, name: str) -> str:
        return f"{self.ns}/{name}"

    def start(self) -> MavrosStandIn:
        n, t = self.node, self._t
        for topic, type_name in (
            ("state", "mavros_msgs/State"),
            ("global_position/global", "sensor_msgs/NavSatFix"),
            ("global_position/local", "nav_msgs/Odometry"),
            ("global_position/compass_hdg", "std_msgs/Float64"),
            ("global_position/rel_alt", "std_msgs/Float64"),
            ("imu/data", "sensor_msgs/Imu"),
        ):
            n.advertise(t(topic), type_name)
        n.subscribe(t("setpoint_raw/local"), "mavros_msgs/PositionTarget", self._on_raw_local)
        n.subscribe(
            t("setpoint_raw/global"), "mavros_msgs/GlobalPositionTarget", self._on_raw_global
        )
        n.subscribe(
            t("setpoint_velocity/cmd_vel_unstamped"), "geometry_msgs/Twist", self._on_cmd_vel
        )
        n.serve(t("set_mode"), "mavros_msgs/SetMode", self._set_mode)
        n.serve(t("cmd/arming"), "mavros_msgs/CommandBool", self._arming)
        self._threads = run_threads("mavros stand-in", self._receive, self._heartbeats)
        return self

    def stop(self) -> None:
        stop_threads(self._stop, self._threads)
        self.mavlink.close()

    # ------------------------------------------------------------------ MAVLink out

    def _heartbeats(self) -> None:
        """The GCS heartbeat (1 Hz); the connection timeout (``conn/timeout``)."""
        n = 0
        while not self._stop.wait(0.25):
            n += 1
            if n % 4 == 0:
                self.mavlink.heartbeat()
            if self.connected and time.monotonic() - self.t_heartbeat > self.conn_timeout_s:
                self.connected = False
                self.node.publish(
                    self._t("state"),
                    {"header": _header(), "connected": False, "mode": "", "system_status": 0},
                )

    def _request_streams(self) -> None:
        us = 1e6 / self.rate_hz
        for msg_id in (mp.MSG_GLOBAL_POSITION_INT, mp.MSG_ATTITUDE):
            self.mavlink.send(
                "command_long_send",
                self.tgt_system, 1, mp.CMD_SET_MESSAGE_INTERVAL, 0, msg_id, us, 0, 0, 0, 0, 0,
            )  # fmt: skip

    # ------------------------------------------------------------------ MAVLink in

    def _receive(self) -> None:
        self.mavlink.receive_loop(
            self._stop,
            {
                "HEARTBEAT": self._on_heartbeat,
                "GLOBAL_POSITION_INT": self._on_global_position,
                "ATTITUDE": self._on_attitude,
                "COMMAND_ACK": self._on_ack,
            },
            timeout_s=0.2,
        )

    def _on_ack(self, msg: Any) -> None:
        slot = self._acks.get(int(msg.command))
        if slot is not None:
            slot[1].append(int(msg.result))
            slot[0].set()

    def _on_heartbeat(self, hb: Any) -> None:
        if hb.type == mp.MAV_TYPE_GCS or hb.autopilot == 8:
            return  # another ground station or companion, not the vehicle
        first = self.tgt_system == 0
        self.tgt_system = hb.get_srcSystem()
        self.autopilot, self.base_mode = int(hb.autopilot), int(hb.base_mode)
        self.t_heartbeat, self.connected = time.monotonic(), True
        if first:
            self._request_streams()
        self.node.publish(
            self._t("state"),
            {
                "header": _header(),
                "connected": True,
                "armed": bool(hb.base_mode & 128),
                "guided": bool(hb.base_mode & 8),
                "manual_input": bool(hb.base_mode & 64),
                "mode": mode_name(self.autopilot, int(hb.custom_mode)),
                "system_status": int(hb.system_status),
            },
        )

    def _on_global_position(self, g: Any) -> None:
        from openconvoy.comms.geodesy import Origin, geodetic_to_enu

        lat, lon, alt = g.lat / 1e7, g.lon / 1e7, g.alt / 1e3
        # One stamp for the message's topics (``synchronized_header``: without time sync,
        # the time it arrived).
        stamp = time.time()
        self.node.publish(
            self._t("global_position/global"),
            {
                "header": {"seq": 0, "stamp": stamp, "frame_id": "base_link"},
                "status": {"status": -1, "service": 1},  # STATUS_NO_FIX, SERVICE_GPS
                "latitude": lat,
                "longitude": lon,
                "altitude": alt,
                "position_covariance": [0.0] * 9,
                "position_covariance_type": 0,
            },
        )
        if self.map_origin is None:
            self.map_origin = (lat, lon, alt)
        x, y, z = geodetic_to_enu(Origin(*self.map_origin), lat, lon, alt)
        self.node.publish(
            self._t("global_position/local"),
            {
                "header": {"seq": 0, "stamp": stamp, "frame_id": "map"},
                "child_frame_id": "base_link",
                "pose": {
                    "pose": {"position": {"x": float(x), "y": float(y), "z": g.relative_alt / 1e3}}
                },
                "twist": {"twist": {"linear": {"x": g.vy / 100, "y": g.vx / 100, "z": g.vz / 100}}},
            },
        )
        hdg = math.nan if g.hdg == 65535 else g.hdg / 100
        self.node.publish(self._t("global_position/compass_hdg"), {"data": hdg})
        self.node.publish(self._t("global_position/rel_alt"), {"data": g.relative_alt / 1e3})

    def _on_attitude(self, a: Any) -> None:
        w, x, y, z = ftf.attitude_ned_to_enu(a.roll, a.pitch, a.yaw)
        self.node.publish(
            self._t("imu/data"),
            {
                "header": _header(frame_id="base_link"),
                "orientation": {"x": x, "y": y, "z": z, "w": w},
                "angular_velocity": {"x": a.rollspeed, "y": -a.pitchspeed, "z": -a.yawspeed},
            },
        )

    # ------------------------------------------------------------------ ROS in

    def _set_mode(self, req: dict[str, Any]) -> dict[str, Any]:
        base_mode = int(req.get("base_mode", 0))
        custom = 0
        if req.get("custom_mode"):
            cm = custom_mode_of(self.autopilot, str(req["custom_mode"]))
            if cm is None:
                return {"mode_sent": False}
            custom = cm
            base_mode |= (self.base_mode & 128) | 1  # SAFETY_ARMED as now, CUSTOM_MODE_ENABLED
        self.mavlink.send("set_mode_send", self.tgt_system, base_mode, custom)
        return {"mode_sent": True}

    def _arming(self, req: dict[str, Any]) -> dict[str, Any] | None:
        slot: tuple[threading.Event, list[int]] = (threading.Event(), [])
        self._acks[mp.CMD_COMPONENT_ARM_DISARM] = slot
        arm = 1.0 if req.get("value") else 0.0
        self.mavlink.send(
            "command_long_send",
            self.tgt_system, 1, mp.CMD_COMPONENT_ARM_DISARM, 1, arm, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip
        if not slot[0].wait(5.0):
            return None  # MAVROS: the service call fails
        result = slot[1][0]
        return {"success": result == mp.RESULT_ACCEPTED, "result": result}

    def _on_raw_local(self, m: dict[str, Any]) -> None:
        v = m.get("velocity", {})
        vn = ftf.transform_frame_enu_ned((v.get("x", 0.0), v.get("y", 0.0), v.get("z", 0.0)))
        p = m.get("position", {})
        pn = ftf.transform_frame_enu_ned((p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0)))
        self.mavlink.send(
            "set_position_target_local_ned_send",
            _ms(m), self.tgt_system, 1, int(m.get("coordinate_frame", 1)), int(m.get("type_mask", 0)),
            *pn, *vn, 0.0, 0.0, 0.0,
            ftf.setpoint_yaw_enu_to_ned(float(m.get("yaw", 0.0))),
            ftf.yaw_rate_enu_to_ned(float(m.get("yaw_rate", 0.0))),
        )  # fmt: skip
        self.setpoints_forwarded += 1

    def _on_raw_global(self, m: dict[str, Any]) -> None:
        v = m.get("velocity", {})
        vn = ftf.transform_frame_enu_ned((v.get("x", 0.0), v.get("y", 0.0), v.get("z", 0.0)))
        self.mavlink.send(
            "set_position_target_global_int_send",
            _ms(m), self.tgt_system, 1, int(m.get("coordinate_frame", 6)), int(m.get("type_mask", 0)),
            int(float(m.get("latitude", 0.0)) * 1e7), int(float(m.get("longitude", 0.0)) * 1e7),
            float(m.get("altitude", 0.0)), *vn, 0.0, 0.0, 0.0,
            ftf.setpoint_yaw_enu_to_ned(float(m.get("yaw", 0.0))),
            ftf.yaw_rate_enu_to_ned(float(m.get("yaw_rate", 0.0))),
        )  # fmt: skip
        self.setpoints_forwarded += 1

    def _on_cmd_vel(self, m: dict[str, Any]) -> None:
        v, a = m.get("linear", {}), m.get("angular", {})
        vn = ftf.transform_frame_enu_ned((v.get("x", 0.0), v.get("y", 0.0), v.get("z", 0.0)))
        self.mavlink.send(
            "set_position_target_local_ned_send",
            int(time.monotonic() * 1000) & 0xFFFFFFFF, self.tgt_system, 1, mp.MAV_FRAME_LOCAL_NED,
            TYPE_MASK_CMD_VEL, 0.0, 0.0, 0.0, *vn, 0.0, 0.0, 0.0,
            0.0, ftf.yaw_rate_enu_to_ned(float(a.get("z", 0.0))),
        )  # fmt: skip
        self.setpoints_forwarded += 1


def _header(frame_id: str = "") -> dict[str, Any]:
    return {"seq": 0, "stamp": time.time(), "frame_id": frame_id}


def _ms(m: dict[str, Any]) -> int:
    """``header.stamp.toNSec() / 1000000`` as MAVLink's uint32 time_boot_ms."""
    stamp = float(m.get("header", {}).get("stamp", 0.0))
    return int(stamp * 1000) & 0xFFFFFFFF
