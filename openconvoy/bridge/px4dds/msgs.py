"""Our definitions of the few px4_msgs types the ``px4-dds`` link uses, as DDS types.

Written from px4_msgs **main at a4a9864b** (github.com/PX4/px4_msgs, "Update to PX4
03bf4a5e95"; the .msg files are PX4-Autopilot's ``msg/`` and ``msg/versioned/``), field for
field and in order, so that the XCDR1 bytes are those of the ``px4_msgs`` a ROS 2 node or
PX4's micro-XRCE-DDS agent uses: ``tests/bridge/test_px4dds_msgs.py`` checks each
against the original ``.msg`` text (``tests/data/px4_msgs/``). Type names are ROS 2's
DDS mangling (``px4_msgs::msg::dds_::VehicleStatus_``), so a real px4_msgs subscriber
matches. ``VERSIONS`` holds each .msg's ``MESSAGE_VERSION``: PX4 (since 1.16) names the
topic of a message with a version N > 0 ``<name>_vN`` (``/fmu/out/vehicle_status_v4``).
Units and frames as in the .msg: NED local frame, radians, microseconds.

Constants are the .msg's, only those we use.
"""

# No ``from __future__ import annotations``: cyclonedds reads these annotations as objects.

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

if TYPE_CHECKING:  # cyclonedds' array types are not generic to mypy; lists at runtime
    F3 = list[float]
    F2 = list[float]
else:
    F3 = t.array[t.float32, 3]
    F2 = t.array[t.float32, 2]

# VehicleCommand.msg
VEHICLE_CMD_DO_SET_MODE = 176
VEHICLE_CMD_COMPONENT_ARM_DISARM = 400
# VehicleCommandAck.msg (same values as MAVLink's MAV_RESULT)
VEHICLE_CMD_RESULT_ACCEPTED = 0
VEHICLE_CMD_RESULT_TEMPORARILY_REJECTED = 1
VEHICLE_CMD_RESULT_DENIED = 2
# VehicleStatus.msg
ARMING_STATE_DISARMED = 1
ARMING_STATE_ARMED = 2
NAVIGATION_STATE_MANUAL = 0
NAVIGATION_STATE_POSCTL = 2
NAVIGATION_STATE_AUTO_LOITER = 4
NAVIGATION_STATE_OFFBOARD = 14
VEHICLE_TYPE_ROVER = 3


def _f3() -> list[float]:
    return [0.0, 0.0, 0.0]


def _nan3() -> list[float]:
    return [float("nan")] * 3


@dataclass
class OffboardControlMode(IdlStruct, typename="px4_msgs::msg::dds_::OffboardControlMode_"):
    """msg/OffboardControlMode.msg (unversioned): which setpoint fields the offboard stream
    controls; its arrival rate is PX4's offboard signal (COM_OF_LOSS_T)."""

    timestamp: t.uint64 = 0
    position: bool = False
    velocity: bool = False
    acceleration: bool = False
    attitude: bool = False
    body_rate: bool = False
    thrust_and_torque: bool = False
    direct_actuator: bool = False


@dataclass
class TrajectorySetpoint(IdlStruct, typename="px4_msgs::msg::dds_::TrajectorySetpoint_"):
    """msg/versioned/TrajectorySetpoint.msg: NED setpoint; NaN = not controlled."""

    timestamp: t.uint64 = 0
    position: F3 = field(default_factory=_nan3)
    velocity: F3 = field(default_factory=_nan3)
    acceleration: F3 = field(default_factory=_nan3)
    jerk: F3 = field(default_factory=_nan3)
    yaw: t.float32 = float("nan")
    yawspeed: t.float32 = float("nan")


@dataclass
class VehicleCommand(IdlStruct, typename="px4_msgs::msg::dds_::VehicleCommand_"):
    """msg/versioned/VehicleCommand.msg: MAVLink's COMMAND_LONG as a uORB message."""

    timestamp: t.uint64 = 0
    param1: t.float32 = 0.0
    param2: t.float32 = 0.0
    param3: t.float32 = 0.0
    param4: t.float32 = 0.0
    param5: t.float64 = 0.0
    param6: t.float64 = 0.0
    param7: t.float32 = 0.0
    command: t.uint32 = 0
    target_system: t.uint8 = 0
    target_component: t.uint8 = 0
    source_system: t.uint8 = 0
    source_component: t.uint16 = 0
    confirmation: t.uint8 = 0
    from_external: bool = False


@dataclass
class VehicleCommandAck(IdlStruct, typename="px4_msgs::msg::dds_::VehicleCommandAck_"):
    """msg/versioned/VehicleCommandAck.msg: the answer to a VehicleCommand."""

    timestamp: t.uint64 = 0
    command: t.uint32 = 0
    result: t.uint8 = 0
    result_param1: t.uint8 = 0
    result_param2: t.int32 = 0
    target_system: t.uint8 = 0
    target_component: t.uint16 = 0
    from_external: bool = False


@dataclass
class VehicleStatus(IdlStruct, typename="px4_msgs::msg::dds_::VehicleStatus_"):
    """msg/versioned/VehicleStatus.msg: commander's state (arming, nav_state, failsafe)."""

    timestamp: t.uint64 = 0
    armed_time: t.uint64 = 0
    takeoff_time: t.uint64 = 0
    arming_state: t.uint8 = 0
    latest_arming_reason: t.uint8 = 0
    latest_disarming_reason: t.uint8 = 0
    nav_state_timestamp: t.uint64 = 0
    nav_state_user_intention: t.uint8 = 0
    nav_state: t.uint8 = 0
    executor_in_charge: t.uint8 = 0
    nav_state_display: t.uint8 = 0
    accepts_offboard_setpoints: bool = False
    valid_nav_states_mask: t.uint32 = 0
    can_set_nav_states_mask: t.uint32 = 0
    hil_state: t.uint8 = 0
    vehicle_type: t.uint8 = 0
    failsafe: bool = False
    failsafe_and_user_took_over: bool = False
    failsafe_defer_state: t.uint8 = 0
    gcs_connection_lost: bool = False
    gcs_connection_lost_counter: t.uint8 = 0
    high_latency_data_link_lost: bool = False
    is_vtol: bool = False
    is_vtol_tailsitter: bool = False
    in_transition_mode: bool = False
    in_transition_to_fw: bool = False
    system_type: t.uint8 = 0
    system_id: t.uint8 = 0
    component_id: t.uint8 = 0
    safety_button_available: bool = False
    safety_off: bool = False
    power_input_valid: bool = False
    usb_connected: bool = False
    open_drone_id_system_present: bool = False
    open_drone_id_system_healthy: bool = False
    parachute_system_present: bool = False
    parachute_system_healthy: bool = False
    traffic_avoidance_system_present: bool = False
    rc_calibration_in_progress: bool = False
    calibration_enabled: bool = False
    pre_flight_checks_pass: bool = False


@dataclass
class VehicleGlobalPosition(IdlStruct, typename="px4_msgs::msg::dds_::VehicleGlobalPosition_"):
    """msg/versioned/VehicleGlobalPosition.msg: the estimator's geodetic position."""

    timestamp: t.uint64 = 0
    timestamp_sample: t.uint64 = 0
    lat: t.float64 = 0.0
    lon: t.float64 = 0.0
    alt: t.float32 = 0.0
    alt_ellipsoid: t.float32 = 0.0
    lat_lon_valid: bool = False
    alt_valid: bool = False
    delta_alt: t.float32 = 0.0
    delta_terrain: t.float32 = 0.0
    lat_lon_reset_counter: t.uint8 = 0
    alt_reset_counter: t.uint8 = 0
    terrain_reset_counter: t.uint8 = 0
    eph: t.float32 = 0.0
    epv: t.float32 = 0.0
    terrain_alt: t.float32 = 0.0
    terrain_alt_valid: bool = False
    dead_reckoning: bool = False


@dataclass
class VehicleLocalPosition(IdlStruct, typename="px4_msgs::msg::dds_::VehicleLocalPosition_"):
    """msg/versioned/VehicleLocalPosition.msg: NED position/velocity from the EKF origin,
    ``heading`` the NED yaw (rad, 0 = north, clockwise)."""

    timestamp: t.uint64 = 0
    timestamp_sample: t.uint64 = 0
    xy_valid: bool = False
    z_valid: bool = False
    v_xy_valid: bool = False
    v_z_valid: bool = False
    x: t.float32 = 0.0
    y: t.float32 = 0.0
    z: t.float32 = 0.0
    delta_xy: F2 = field(default_factory=lambda: [0.0, 0.0])
    xy_reset_counter: t.uint8 = 0
    delta_z: t.float32 = 0.0
    z_reset_counter: t.uint8 = 0
    vx: t.float32 = 0.0
    vy: t.float32 = 0.0
    vz: t.float32 = 0.0
    z_deriv: t.float32 = 0.0
    delta_vxy: F2 = field(default_factory=lambda: [0.0, 0.0])
    vxy_reset_counter: t.uint8 = 0
    delta_vz: t.float32 = 0.0
    vz_reset_counter: t.uint8 = 0
    ax: t.float32 = 0.0
    ay: t.float32 = 0.0
    az: t.float32 = 0.0
    heading: t.float32 = 0.0
    heading_var: t.float32 = 0.0
    unaided_heading: t.float32 = 0.0
    delta_heading: t.float32 = 0.0
    heading_reset_counter: t.uint8 = 0
    heading_good_for_control: bool = False
    tilt_var: t.float32 = 0.0
    xy_global: bool = False
    z_global: bool = False
    ref_timestamp: t.uint64 = 0
    ref_lat: t.float64 = 0.0
    ref_lon: t.float64 = 0.0
    ref_alt: t.float32 = 0.0
    dist_bottom_valid: bool = False
    dist_bottom: t.float32 = 0.0
    dist_bottom_var: t.float32 = 0.0
    delta_dist_bottom: t.float32 = 0.0
    dist_bottom_reset_counter: t.uint8 = 0
    dist_bottom_sensor_bitfield: t.uint8 = 0
    eph: t.float32 = 0.0
    epv: t.float32 = 0.0
    evh: t.float32 = 0.0
    evv: t.float32 = 0.0
    dead_reckoning: bool = False
    vxy_max: t.float32 = 0.0
    vz_max: t.float32 = 0.0
    hagl_min: t.float32 = 0.0
    hagl_max_z: t.float32 = 0.0
    hagl_max_xy: t.float32 = 0.0


ALL = (
    OffboardControlMode,
    TrajectorySetpoint,
    VehicleCommand,
    VehicleCommandAck,
    VehicleStatus,
    VehicleGlobalPosition,
    VehicleLocalPosition,
)
"""Every type here, for the field-by-field check against the .msg files."""

VERSIONS: dict[str, int] = {
    "OffboardControlMode": 0,
    "TrajectorySetpoint": 0,
    "VehicleCommand": 0,
    "VehicleCommandAck": 1,
    "VehicleStatus": 4,
    "VehicleGlobalPosition": 0,
    "VehicleLocalPosition": 1,
}
"""Each type's ``MESSAGE_VERSION`` in px4_msgs a4a9864b (checked against the .msg files)."""


def topic_base(data_type: type) -> str:
    """The topic's last name part for a px4_msgs type: its snake_case name, ``_vN`` for a
    versioned message (``VehicleStatus`` -> ``vehicle_status_v4``)."""
    name = "".join("_" + c.lower() if c.isupper() else c for c in data_type.__name__).lstrip("_")
    version = VERSIONS[data_type.__name__]
    return f"{name}_v{version}" if version else name
