"""The ROS 2 types the ``ap-dds`` link uses, as DDS types for Cyclone DDS: the link then
needs no ROS install (``cyclone_agent.py``).

Written field for field, in order, from the interface text of ROS 2 Jazzy
(``builtin_interfaces/msg/Time`` and ``std_msgs/msg/Header`` from ``comms.dds``,
``sensor_msgs/msg/NavSatStatus``,
``NavSatFix``, ``geometry_msgs/msg/Point``, ``Quaternion``, ``Pose``, ``PoseStamped``,
``Vector3``, ``Twist``, ``TwistStamped``) and ArduPilot's ``ardupilot_msgs``
(``msg/Status.msg``, ``srv/ArmMotors.srv``, ``srv/ModeSwitch.srv``; our copies in
``ardupilot_msgs/``, checked against ArduPilot's in ``tests/data/ros/ardupilot-msgs``).
Type names are rosidl's DDS mangling (``pkg::msg::dds_::T_``; a service's request and
response ``pkg::srv::dds_::T_Request_`` / ``T_Response_``), as ArduPilot's
``AP_DDS_Topic_Table.h`` and ``AP_DDS_Service_Table.h`` name them, so the XCDR1 bytes are
those rclpy or AP_DDS exchange. ``tests/bridge/test_apdds_cyclone.py`` checks every field
against rclpy's own classes and ArduPilot's .msg text.
"""

# No ``from __future__ import annotations``: cyclonedds reads these annotations as objects.

import math
from dataclasses import dataclass, field, fields, is_dataclass
from typing import TYPE_CHECKING, Any

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

from openconvoy.comms.dds import Header, Time

if TYPE_CHECKING:  # cyclonedds' container types are not generic to mypy; lists at runtime
    F9 = list[float]
    U8Seq = list[int]
else:
    F9 = t.array[t.float64, 9]
    U8Seq = t.sequence[t.uint8]


@dataclass
class NavSatStatus(IdlStruct, typename="sensor_msgs::msg::dds_::NavSatStatus_"):
    status: t.int8 = 0
    service: t.uint16 = 0


@dataclass
class NavSatFix(IdlStruct, typename="sensor_msgs::msg::dds_::NavSatFix_"):
    header: Header = field(default_factory=Header)
    status: NavSatStatus = field(default_factory=NavSatStatus)
    latitude: t.float64 = 0.0
    longitude: t.float64 = 0.0
    altitude: t.float64 = 0.0
    position_covariance: F9 = field(default_factory=lambda: [0.0] * 9)
    position_covariance_type: t.uint8 = 0


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class Status(IdlStruct, typename="ardupilot_msgs::msg::dds_::Status_"):
    header: Header = field(default_factory=Header)
    vehicle_type: t.uint8 = 0
    armed: bool = False
    mode: t.uint8 = 0
    flying: bool = False
    external_control: bool = False
    failsafe: U8Seq = field(default_factory=list)


@dataclass
class ArmMotors_Request(IdlStruct, typename="ardupilot_msgs::srv::dds_::ArmMotors_Request_"):
    arm: bool = False


@dataclass
class ArmMotors_Response(IdlStruct, typename="ardupilot_msgs::srv::dds_::ArmMotors_Response_"):
    result: bool = False


@dataclass
class ModeSwitch_Request(IdlStruct, typename="ardupilot_msgs::srv::dds_::ModeSwitch_Request_"):
    mode: t.uint8 = 0


@dataclass
class ModeSwitch_Response(IdlStruct, typename="ardupilot_msgs::srv::dds_::ModeSwitch_Response_"):
    status: bool = False
    curr_mode: t.uint8 = 0


MESSAGES: dict[str, type] = {
    "sensor_msgs/NavSatFix": NavSatFix,
    "geometry_msgs/PoseStamped": PoseStamped,
    "geometry_msgs/TwistStamped": TwistStamped,
    "ardupilot_msgs/Status": Status,
}
"""Message types by the ``pkg/Type`` names the link uses."""

SERVICES: dict[str, tuple[type, type]] = {
    "ardupilot_msgs/ArmMotors": (ArmMotors_Request, ArmMotors_Response),
    "ardupilot_msgs/ModeSwitch": (ModeSwitch_Request, ModeSwitch_Response),
}
"""Service types (request, response) by ``pkg/Type``."""


def to_dict(value: Any) -> Any:
    """A sample as the link's dict (``Time`` as float seconds, arrays as lists)."""
    if isinstance(value, Time):
        return value.sec + value.nanosec * 1e-9
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_dict(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, (list, tuple)):
        return [to_dict(v) for v in value]
    return value


def from_dict(cls: type, data: Any) -> Any:
    """A sample of ``cls`` from ``to_dict``'s data (missing fields default; a non-finite
    or negative time is 0)."""
    if cls is Time:
        s = float(data) if isinstance(data, (int, float)) and math.isfinite(data) else 0.0
        sec = int(max(s, 0.0) // 1)
        return Time(sec, min(int(round((max(s, 0.0) - sec) * 1e9)), 999_999_999))
    msg = cls()
    for f in fields(msg):
        if not isinstance(data, dict) or f.name not in data:
            continue
        current = getattr(msg, f.name)
        v = data[f.name]
        if is_dataclass(current):
            v = from_dict(type(current), v)
        elif isinstance(current, bool):
            v = bool(v)
        elif isinstance(current, int):
            v = int(v)
        elif isinstance(current, float):
            v = float(v)
        elif isinstance(current, list):
            v = list(v)
        setattr(msg, f.name, v)
    return msg
