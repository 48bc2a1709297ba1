"""``ApDdsLink``: an ArduPilot Rover through its own ROS 2 interface, AP_DDS (``--link ap-dds``),
behind the same ``VehicleLink`` protocol as ``MavlinkLink``.

Names, types and QoS from ArduPilot's source (github.com/ArduPilot/ardupilot,
``libraries/AP_DDS/AP_DDS_Topic_Table.h``, ``AP_DDS_Service_Table.h``,
``AP_DDS_ExternalControl.cpp``; ``Rover/AP_ExternalControl_Rover.cpp``), under ``ns``
(default ``/ap``; AP_DDS's topics are ``rt/ap/...``):

- ``/ap/navsat`` (``sensor_msgs/NavSatFix``, best effort): latitude, longitude → our ENU
  around the convoy origin; its stamp is the state's time; it keeps the telemetry fresh
  and, since AP_DDS publishes ``/ap/status`` only when it changes, also plays the heartbeat.
- ``/ap/pose/filtered`` (``geometry_msgs/PoseStamped``, ENU, best effort): the heading is
  the orientation's yaw.
- ``/ap/twist/filtered`` (``geometry_msgs/TwistStamped``, best effort): linear = ENU velocity
  (speed = its part along the heading), angular.z = the yaw rate (FLU, counter-clockwise).
- ``/ap/status`` (``ardupilot_msgs/Status``, reliable, transient local): armed, mode number
  (Rover's ``ROVER_MODE``: 15 GUIDED, 4 HOLD).
- ``/ap/mode_switch`` (``ardupilot_msgs/srv/ModeSwitch``: mode → status, curr_mode) and
  ``/ap/arm_motors`` (``ardupilot_msgs/srv/ArmMotors``: arm → result).

Commands: ``/ap/cmd_vel`` (``geometry_msgs/TwistStamped``, best effort), header.frame_id
``base_link``: AP_DDS rotates body FLU (x forward, y left, z up) to NED and negates
angular.z (``AP_DDS_External_Control::handle_velocity_control``); Rover turns that back into
the body-forward speed and a turn rate (``AP_ExternalControl_Rover::
set_linear_velocity_and_yaw_rate``: ``earth_to_body``, ``set_desired_turn_rate_and_speed``),
only in GUIDED while armed. So linear.x = the signed body-forward speed (negative reverses)
and there is **no absolute heading**: this link closes its own heading loop,
angular.z = clamp(``HEADING_P`` × wrap(heading − current heading), ±``MAX_RATE``), ENU
(counter-clockwise positive) — ArduPilot's own heading controller with its defaults
(``ATC_STR_ANG_P`` 2, ``ATC_STR_RAT_MAX`` 120°/s), run here on the latest pose.

Arming: GUIDED by ``mode_switch`` (confirmed on ``/ap/status``), then ``arm_motors``,
retried while refused up to the timeout; a mode change away from GUIDED this link did not
ask for latches ``pilot_took_over`` (as ``MavrosLink``).
"""

from __future__ import annotations

import math
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.ros.mavros_link import MavrosLink
from openconvoy.bridge.ros.mavros_standin import ROVER_CMODES, custom_mode_of

HEADING_P = 2.0
"""Turn rate per radian of heading error (1/s): ArduPilot Rover's ``ATC_STR_ANG_P`` default."""
MAX_RATE = math.radians(120.0)
"""The turn-rate limit (rad/s): ArduPilot Rover's ``ATC_STR_RAT_MAX`` default."""


def enu_yaw(q: dict[str, Any]) -> float:
    """The yaw (rad, ENU, counter-clockwise from east) of a quaternion dict (x, y, z, w)."""
    x, y, z, w = (float(q.get(k, 0.0)) for k in ("x", "y", "z", "w"))
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def yaw_rate_for(heading_rad: float, current_rad: float) -> float:
    """The link's heading loop: the ENU turn rate (rad/s) toward ``heading_rad``."""
    rate = HEADING_P * wrap_pi(heading_rad - current_rad)
    return max(-MAX_RATE, min(MAX_RATE, rate))


class ApDdsLink(MavrosLink):
    """ArduPilot Rover ``vehicle_id`` through AP_DDS's topics under ``ns`` (``/ap``; one per
    vehicle, e.g. ``/vehicle_1/ap``); ``MavrosLink``'s arguments, the firmware fixed
    (``node_factory`` makes this link's ROS 2 node)."""

    FIRMWARE = "ardupilot"

    # ------------------------------------------------------------------ callbacks

    def _on_status(self, m: dict[str, Any]) -> None:
        with self._lock:
            self._connected = True
            mode = int(m.get("mode", 0))
            self._mode = ROVER_CMODES.get(mode, f"CMODE({mode})")
            self._armed = bool(m.get("armed"))
            self._t_state = self.clock()

    def _on_fix(self, m: dict[str, Any]) -> None:
        super()._on_fix(m)
        with self._lock:
            if self._connected:
                self._t_state = self.clock()  # status comes only on change: this is the pulse

    def _on_pose(self, m: dict[str, Any]) -> None:
        yaw = enu_yaw(m.get("pose", {}).get("orientation", {}))
        with self._lock:
            self._hdg = (90.0 - math.degrees(yaw)) % 360.0  # compass degrees, as MavrosLink
            self._new_hdg = True

    def _on_twist(self, m: dict[str, Any]) -> None:
        tw = m.get("twist", {})
        lin, ang = tw.get("linear", {}), tw.get("angular", {})
        with self._lock:
            self._vel = (float(lin.get("x", 0.0)), float(lin.get("y", 0.0)))
            self._yaw_rate = float(ang.get("z", 0.0))

    def _open(self) -> None:
        self._reset_state()
        node = self.node_factory()
        t = self._t
        node.subscribe(t("status"), "ardupilot_msgs/Status", self._on_status)
        node.subscribe(t("navsat"), "sensor_msgs/NavSatFix", self._on_fix)
        node.subscribe(t("pose/filtered"), "geometry_msgs/PoseStamped", self._on_pose)
        node.subscribe(t("twist/filtered"), "geometry_msgs/TwistStamped", self._on_twist)
        node.advertise(t("cmd_vel"), "geometry_msgs/TwistStamped")
        self._node, self._closed = node, False

    # ------------------------------------------------------------------ commands

    def _set_mode(self, name: str) -> bool:
        self._requested = name
        number = custom_mode_of(mp.AUTOPILOT_ARDUPILOT, name)
        if number is None:
            return False
        r = self._call("mode_switch", "ardupilot_msgs/ModeSwitch", {"mode": number})
        return bool(r.get("status"))

    def _arm_call(self, value: bool, timeout_s: float = 5.0) -> dict[str, Any]:
        r = self._call("arm_motors", "ardupilot_msgs/ArmMotors", {"arm": value}, timeout_s)
        ok = bool(r.get("result"))
        # ArmMotors answers a bool only: a refusal has no MAV_RESULT to report.
        return {"success": ok, "result": mp.RESULT_ACCEPTED if ok else mp.RESULT_FAILED}

    def _publish_setpoint(self, speed_mps: float, heading_rad: float) -> None:
        node = self._node_or_lost()
        current = self._heading_now()
        rate = yaw_rate_for(float(heading_rad), current) if speed_mps != 0.0 else 0.0
        msg: dict[str, Any] = {
            "header": {"stamp": self.wall(), "frame_id": "base_link"},
            "twist": {
                "linear": {"x": float(speed_mps), "y": 0.0, "z": 0.0},
                "angular": {"x": 0.0, "y": 0.0, "z": rate},
            },
        }
        node.publish(self._t("cmd_vel"), msg)
        self.commands_sent += 1
        self._last_sp = (float(speed_mps), float(heading_rad), self.clock())
