"""A stand-in for ArduPilot's AP_DDS: the ROS 2 side of an ArduPilot Rover, forwarding to our
simulated ArduPilot (``bridge.simvehicle``) over real MAVLink.

AP_DDS runs inside the firmware (a Micro XRCE-DDS client behind an agent); SITL is not
available to our CI, so tests and ``demo --link ap-dds`` run this rclpy node in its place.
It offers AP_DDS's names, types and QoS (github.com/ArduPilot/ardupilot, master as
indexed: ``libraries/AP_DDS/AP_DDS_Topic_Table.h``, ``AP_DDS_Service_Table.h``,
``AP_DDS_ExternalControl.cpp``, ``Rover/AP_ExternalControl_Rover.cpp``):

- ``/ap/navsat`` (NavSatFix), ``/ap/pose/filtered`` (PoseStamped, ENU position from the
  first fix, orientation ENU/FLU), ``/ap/twist/filtered`` (TwistStamped: ENU velocity,
  FLU body rates), all best effort, from each GLOBAL_POSITION_INT / ATTITUDE;
  ``/ap/status`` (``ardupilot_msgs/Status``, reliable, transient local) when armed or mode
  change (AP_DDS publishes it on change), vehicle_type APM_ROVER.
- ``/ap/cmd_vel`` (TwistStamped): ``handle_velocity_control``: frame ``base_link`` (FLU
  rotated to NED by the current yaw) or ``map`` (ENU → NED: (y, x, −z)), yaw rate =
  −angular.z; any other frame is dropped. Rover then (``set_linear_velocity_and_yaw_rate``)
  takes only the body-forward part (``earth_to_body(...).x``) and the turn rate, in GUIDED
  while armed: ``set_desired_turn_rate_and_speed``. Over MAVLink the same target is
  SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED with vx = that signed speed, vy = 0,
  type_mask 1479 (velocity + yaw rate), which GCS_MAVLink_Rover.cpp hands to the same call.
- ``/ap/mode_switch`` (ModeSwitch: mode number → MAVLink SET_MODE; ``status`` when the
  vehicle reports that mode within 1 s, ``curr_mode`` the mode then) and ``/ap/arm_motors``
  (ArmMotors: COMMAND_LONG COMPONENT_ARM_DISARM, ``result`` = ACCEPTED).

Not modelled: the other AP_DDS topics (time, clock, tf, battery, imu, geopose, goal, rc,
joy, global position control), ``/ap/prearm_check`` (std_srvs/Trigger on newer AP_DDS),
the XRCE agent itself.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.companion import run_threads
from openconvoy.bridge.ros import ftf
from openconvoy.bridge.ros.mavros_standin import TYPE_MASK_CMD_VEL, MavrosStandIn

MAV_FRAME_BODY_NED = 8
APM_ROVER = 1


def body_forward_speed(m: dict[str, Any], yaw_ned: float) -> float | None:
    """``handle_velocity_control`` then Rover's ``earth_to_body(...).x``: the body-forward
    speed a ``/ap/cmd_vel`` asks of a rover at NED yaw ``yaw_ned`` (None: frame dropped)."""
    lin = m.get("twist", {}).get("linear", {})
    x, y = float(lin.get("x", 0.0)), float(lin.get("y", 0.0))
    frame = m.get("header", {}).get("frame_id", "")
    if frame == "base_link":
        # FLU → FRD (y negated) → earth by yaw, then back to body: the forward part is x.
        n = x * math.cos(yaw_ned) + y * math.sin(yaw_ned)
        e = x * math.sin(yaw_ned) - y * math.cos(yaw_ned)
    elif frame == "map":
        n, e = y, x  # ENU → NED
    else:
        return None
    return n * math.cos(yaw_ned) + e * math.sin(yaw_ned)


class ApDdsStandIn(MavrosStandIn):
    """The stand-in node: ROS 2 side ``node`` (a ``Ros2Node``) with AP_DDS's names under
    ``ns`` (``/ap``), MAVLink side ``mavlink_url``. ``start`` begins; ``stop`` ends."""

    def __init__(self, node: Any, mavlink_url: str, ns: str = "/ap", rate_hz: float = 20.0):
        super().__init__(node, mavlink_url, ns, rate_hz)
        self.yaw_ned = 0.0
        self.custom_mode = -1
        self.armed = False
        self.commands_dropped = 0
        self._rates = (0.0, 0.0, 0.0)
        self._mode_seen = threading.Condition()

    def start(self) -> ApDdsStandIn:
        n, t = self.node, self._t
        n.advertise(t("status"), "ardupilot_msgs/Status", latch=True)
        for topic, type_name in (
            ("navsat", "sensor_msgs/NavSatFix"),
            ("pose/filtered", "geometry_msgs/PoseStamped"),
            ("twist/filtered", "geometry_msgs/TwistStamped"),
        ):
            n.advertise(t(topic), type_name)
        n.subscribe(t("cmd_vel"), "geometry_msgs/TwistStamped", self._on_ap_cmd_vel)
        n.serve(t("mode_switch"), "ardupilot_msgs/ModeSwitch", self._mode_switch)
        n.serve(t("arm_motors"), "ardupilot_msgs/ArmMotors", self._arm_motors)
        self._threads = run_threads("ap_dds stand-in", self._receive, self._heartbeats)
        return self

    # ------------------------------------------------------------------ MAVLink in

    def _heartbeats(self) -> None:
        while not self._stop.wait(1.0):
            self.mavlink.heartbeat()  # the XRCE side is not MAVLink: ours

    def _on_heartbeat(self, hb: Any) -> None:
        if hb.type == mp.MAV_TYPE_GCS or hb.autopilot == 8:
            return
        first = self.tgt_system == 0
        self.tgt_system = hb.get_srcSystem()
        self.autopilot, self.base_mode = int(hb.autopilot), int(hb.base_mode)
        armed, mode = bool(hb.base_mode & 128), int(hb.custom_mode)
        if first:
            self._request_streams()
        if first or armed != self.armed or mode != self.custom_mode:
            with self._mode_seen:
                self.armed, self.custom_mode = armed, mode
                self._mode_seen.notify_all()
            self.node.publish(
                self._t("status"),
                {
                    "header": _header("base_link"),
                    "vehicle_type": APM_ROVER,
                    "armed": armed,
                    "mode": mode,
                    "flying": armed,
                    "external_control": True,
                    "failsafe": [],
                },
            )

    def _on_global_position(self, g: Any) -> None:
        from openconvoy.comms.geodesy import Origin, geodetic_to_enu

        lat, lon, alt = g.lat / 1e7, g.lon / 1e7, g.alt / 1e3
        stamp = time.time()
        self.node.publish(
            self._t("navsat"),
            {
                "header": {"stamp": stamp, "frame_id": "GPS_0"},
                "status": {"status": 0, "service": 1},
                "latitude": lat,
                "longitude": lon,
                "altitude": alt,
                "position_covariance_type": 0,
            },
        )
        if self.map_origin is None:
            self.map_origin = (lat, lon, alt)
        x, y, z = geodetic_to_enu(Origin(*self.map_origin), lat, lon, alt)
        w, qx, qy, qz = ftf.attitude_ned_to_enu(0.0, 0.0, self.yaw_ned)
        self.node.publish(
            self._t("pose/filtered"),
            {
                "header": {"stamp": stamp, "frame_id": "map"},
                "pose": {
                    "position": {"x": float(x), "y": float(y), "z": float(z)},
                    "orientation": {"x": qx, "y": qy, "z": qz, "w": w},
                },
            },
        )
        rx, ry, rz = self._rates
        self.node.publish(
            self._t("twist/filtered"),
            {
                "header": {"stamp": stamp, "frame_id": "base_link"},
                "twist": {
                    "linear": {"x": g.vy / 100, "y": g.vx / 100, "z": -g.vz / 100},
                    "angular": {"x": rx, "y": ry, "z": rz},
                },
            },
        )

    def _on_attitude(self, a: Any) -> None:
        self.yaw_ned = float(a.yaw)
        self._rates = (a.rollspeed, -a.pitchspeed, -a.yawspeed)

    # ------------------------------------------------------------------ ROS in

    def _mode_switch(self, req: dict[str, Any]) -> dict[str, Any]:
        mode = int(req.get("mode", 0))
        self.mavlink.send("set_mode_send", self.tgt_system, (self.base_mode & 128) | 1, mode)
        deadline = time.monotonic() + 1.0
        with self._mode_seen:
            while self.custom_mode != mode and time.monotonic() < deadline:
                self._mode_seen.wait(0.05)
            return {"status": self.custom_mode == mode, "curr_mode": max(self.custom_mode, 0)}

    def _arm_motors(self, req: dict[str, Any]) -> dict[str, Any]:
        r = self._arming({"value": bool(req.get("arm"))})
        return {"result": bool(r and r.get("success"))}

    def _on_ap_cmd_vel(self, m: dict[str, Any]) -> None:
        speed = body_forward_speed(m, self.yaw_ned)
        if speed is None:
            self.commands_dropped += 1
            return
        rate_ned = ftf.yaw_rate_enu_to_ned(float(m["twist"].get("angular", {}).get("z", 0.0)))
        self.mavlink.send(
            "set_position_target_local_ned_send",
            int(time.monotonic() * 1000) & 0xFFFFFFFF, self.tgt_system, 1, MAV_FRAME_BODY_NED,
            TYPE_MASK_CMD_VEL, 0.0, 0.0, 0.0, speed, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, rate_ned,
        )  # fmt: skip
        self.setpoints_forwarded += 1


def _header(frame_id: str = "") -> dict[str, Any]:
    return {"stamp": time.time(), "frame_id": frame_id}
