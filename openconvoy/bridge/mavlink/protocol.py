"""MAVLink facts shared by the link and the simulated vehicle (shared/AUTOPILOTS.md).

Mode numbers, the PX4 ``custom_mode`` encoding, setpoint type masks, and access to
pymavlink with MAVLink 2 (what ArduPilot and PX4 speak). pymavlink keeps its dialect in a
module global, so code here always reads ``mavutil.mavlink`` at call time.
"""

from __future__ import annotations

import os
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its dialect at import

from pymavlink import mavutil  # noqa: E402

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":  # imported earlier without MAVLINK20
    os.environ["MAVLINK20"] = "1"
    mavutil.set_dialect("ardupilotmega")


def mav() -> Any:
    """The pymavlink dialect module in use (message classes and enums)."""
    return mavutil.mavlink


AUTOPILOT_ARDUPILOT = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
AUTOPILOT_PX4 = 12  # MAV_AUTOPILOT_PX4
MAV_TYPE_GROUND_ROVER = 10
MAV_TYPE_GCS = 6

# ArduPilot Rover custom_mode numbers.
ROVER_MODES: dict[int, str] = {0: "MANUAL", 4: "HOLD", 10: "AUTO", 15: "GUIDED"}
ROVER_MODE_NUMBERS: dict[str, int] = {v: k for k, v in ROVER_MODES.items()}

# PX4 custom_mode = main_mode << 16 | sub_mode << 24 (px4_custom_mode.h).
PX4_MAIN_MANUAL = 1
PX4_MAIN_POSCTL = 3
PX4_MAIN_AUTO = 4
PX4_MAIN_OFFBOARD = 6
PX4_SUB_AUTO_LOITER = 3
PX4_MODES: dict[tuple[int, int], str] = {
    (PX4_MAIN_MANUAL, 0): "MANUAL",
    (PX4_MAIN_POSCTL, 0): "POSCTL",
    (PX4_MAIN_AUTO, PX4_SUB_AUTO_LOITER): "LOITER",
    (PX4_MAIN_OFFBOARD, 0): "OFFBOARD",
}
PX4_MODE_NUMBERS: dict[str, tuple[int, int]] = {v: k for k, v in PX4_MODES.items()}


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 heartbeat ``custom_mode`` for a main/sub mode pair."""
    return (main & 0xFF) << 16 | (sub & 0xFF) << 24


def px4_mode_parts(custom_mode: int) -> tuple[int, int]:
    """(main, sub) from a PX4 heartbeat ``custom_mode``."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(autopilot: int, custom_mode: int) -> str:
    """Human mode name from a heartbeat's autopilot and custom_mode."""
    if autopilot == AUTOPILOT_PX4:
        main, sub = px4_mode_parts(custom_mode)
        if main == PX4_MAIN_AUTO:
            return PX4_MODES.get((main, sub), f"AUTO:{sub}")
        return PX4_MODES.get((main, 0), f"PX4:{main}")
    return ROVER_MODES.get(custom_mode, f"MODE{custom_mode}")


# SET_POSITION_TARGET_* type_mask bits (POSITION_TARGET_TYPEMASK): a set bit = ignore.
MASK_POS = 0b111
MASK_VEL = 0b111 << 3
MASK_ACC = 0b111 << 6
MASK_FORCE = 1 << 9
MASK_YAW = 1 << 10
MASK_YAW_RATE = 1 << 11
TYPE_MASK_VEL_YAW = MASK_POS | MASK_ACC | MASK_YAW_RATE  # 2503: velocity + yaw
TYPE_MASK_VEL = MASK_POS | MASK_ACC | MASK_YAW | MASK_YAW_RATE  # 3527: velocity only
assert TYPE_MASK_VEL_YAW == 2503 and TYPE_MASK_VEL == 3527

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = 6

CMD_DO_SET_MODE = 176
CMD_COMPONENT_ARM_DISARM = 400
CMD_SET_MESSAGE_INTERVAL = 511
MSG_ATTITUDE = 30
MSG_LOCAL_POSITION_NED = 32
MSG_GLOBAL_POSITION_INT = 33
MSG_VFR_HUD = 74

RESULT_ACCEPTED = 0
RESULT_TEMPORARILY_REJECTED = 1
RESULT_DENIED = 2
RESULT_UNSUPPORTED = 3
RESULT_FAILED = 4


def command_name(command: int) -> str:
    """``MAV_CMD_...`` name of a command id (the number if unknown)."""
    entry = mav().enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD {command}"


def result_name(result: int) -> str:
    """``MAV_RESULT_...`` name of a COMMAND_ACK result."""
    entry = mav().enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


def message_name(msg_id: int) -> str:
    """Message name of a MAVLink message id (the number if unknown)."""
    cls = mav().mavlink_map.get(msg_id)
    return cls.msgname if cls is not None else f"message {msg_id}"
