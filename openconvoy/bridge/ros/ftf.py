"""MAVROS's frame conversions, as its ``ftf`` library computes them (pure functions).

Followed: github.com/mavlink/mavros tag 1.4.0, ``mavros/src/lib/ftf_frame_conversions.cpp``
and ``ftf_quaternion_utils.cpp``: ``NED_ENU_Q = quaternion_from_rpy(π, 0, π/2)``,
``AIRCRAFT_BASELINK_Q = quaternion_from_rpy(π, 0, 0)``; vectors ENU↔NED by swapping x and y
and negating z (``NED_ENU_REFLECTION_XY``, ``NED_ENU_REFLECTION_Z``); orientations
``transform_orientation_ned_enu(q) = NED_ENU_Q * q`` and
``transform_orientation_aircraft_baselink(q) = q * AIRCRAFT_BASELINK_Q`` (FLU ↔ FRD body).

Quaternions are ``(w, x, y, z)`` tuples; angles in radians.
"""

from __future__ import annotations

import math

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> Quat:
    """``ftf::quaternion_from_rpy``: Z-Y-X (yaw, then pitch, then roll) Euler angles."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def qmul(a: Quat, b: Quat) -> Quat:
    """Hamilton product ``a * b`` (Eigen's ``operator*``)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quaternion_get_yaw(q: Quat) -> float:
    """``ftf::quaternion_get_yaw``: the Z-Y-X yaw of ``q`` (rad, −π..π)."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


NED_ENU_Q = quaternion_from_rpy(math.pi, 0.0, math.pi / 2)
AIRCRAFT_BASELINK_Q = quaternion_from_rpy(math.pi, 0.0, 0.0)


def transform_frame_enu_ned(v: Vec3) -> Vec3:
    """A vector from ENU to NED (and back: the map is its own inverse)."""
    return (v[1], v[0], -v[2])


transform_frame_ned_enu = transform_frame_enu_ned


def setpoint_yaw_enu_to_ned(yaw_enu: float) -> float:
    """The yaw MAVROS's ``setpoint_raw`` puts in a SET_POSITION_TARGET_* message for a
    ``PositionTarget``/``GlobalPositionTarget`` ``yaw`` (ENU, rad): ``quaternion_get_yaw(
    transform_orientation_aircraft_baselink(transform_orientation_ned_enu(
    quaternion_from_rpy(0, 0, yaw))))`` (``setpoint_raw.cpp`` ``local_cb``/``global_cb``),
    which equals π/2 − yaw, wrapped."""
    q = quaternion_from_rpy(0.0, 0.0, yaw_enu)
    return quaternion_get_yaw(qmul(qmul(NED_ENU_Q, q), AIRCRAFT_BASELINK_Q))


def yaw_rate_enu_to_ned(rate_enu: float) -> float:
    """``transform_frame_ned_enu((0, 0, rate)).z``: a yaw rate from ENU (CCW) to NED (CW)."""
    return transform_frame_ned_enu((0.0, 0.0, rate_enu))[2]


def attitude_ned_to_enu(roll: float, pitch: float, yaw_ned: float) -> Quat:
    """The ENU/FLU orientation MAVROS's ``imu`` plugin publishes for a MAVLink ATTITUDE
    (``imu.cpp`` ``handle_attitude``: ``transform_orientation_aircraft_baselink(
    transform_orientation_ned_enu(quaternion_from_rpy(roll, pitch, yaw)))``)."""
    q = quaternion_from_rpy(roll, pitch, yaw_ned)
    return qmul(qmul(NED_ENU_Q, q), AIRCRAFT_BASELINK_Q)


def compass_hdg_to_enu_heading(hdg_deg: float) -> float:
    """``/mavros/global_position/compass_hdg`` (degrees, 0 = north, clockwise: GLOBAL_
    POSITION_INT.hdg / 100, ``global_position.cpp``) as an ENU heading (rad, 0 = east, CCW,
    −π..π)."""
    h = math.pi / 2 - math.radians(hdg_deg)
    return math.atan2(math.sin(h), math.cos(h))
