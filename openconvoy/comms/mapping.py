"""Internal vehicle state (local ENU, SI) <-> BSM core (J2735 units), and BSM time.

Positions go through geodetic coordinates around the convoy ``Origin`` (pymap3d via
``geodesy``). Headings convert between the ENU convention (radians, 0 = east,
counter-clockwise) and J2735's compass heading (0.0125 degree units, 0 = north,
clockwise). Out-of-range values clamp to the standard's limits, never wrap; heading is an
angle, so it is taken modulo 360 degrees (359.99 and -0.01 degrees are the same heading).

Time: a BSM carries only ``secMark``, the milliseconds within the UTC minute of the
sender's measurement. The receiver rebuilds the full send time from its own receive time:
the latest time with that ``secMark`` not after the receive time (plus a small tolerance
for clocks a little ahead), clamped to the receive time, so message age is never negative.
"""

from __future__ import annotations

import math

from openconvoy.comms import bsm as j
from openconvoy.comms.geodesy import Origin, enu_to_geodetic, geodetic_to_enu
from openconvoy.core.state import VehicleState, wrap_angle

#: The link's one clock tolerance (s): the slack for a sender clock ahead of the
#: receiver's in the secMark rebuild, the replay window of signed messages
#: (``security.auth``) and the largest clock offset the convoy start accepts
#: (``[v2v] replay_window_s`` sets all three).
DEFAULT_TIME_TOLERANCE_S = 1.0


def _clamp(v: int, lo: int, hi: int) -> int:
    return lo if v < lo else hi if v > hi else v


def _quantize(value: float, unit: float, lo: int, hi: int) -> int:
    """Round ``value / unit`` to the nearest integer and clamp it to [lo, hi]."""
    q = value / unit
    if not math.isfinite(q):
        # +-inf saturate like any huge value; NaN has no meaningful code: callers that
        # can say "unavailable" check for it before quantizing.
        if math.isnan(q):
            raise ValueError("cannot quantize NaN")
        return hi if q > 0 else lo
    return _clamp(round(q), lo, hi)


def _quantize_or(value: float, unit: float, lo: int, hi: int, unavailable: int) -> int:
    """Like ``_quantize`` but NaN (unknown) maps to the field's "unavailable" code."""
    return unavailable if math.isnan(value) else _quantize(value, unit, lo, hi)


def sec_mark(t: float) -> int:
    """``secMark`` of time ``t`` (seconds on the shared clock, e.g. Unix time): ms in minute.

    Truncates to the millisecond, so the time rebuilt from it is never later than ``t``.
    """
    return int(math.floor(t * 1000.0)) % 60000


def reconstruct_send_time(
    sec_mark_ms: int, t_rx: float, tolerance_s: float = DEFAULT_TIME_TOLERANCE_S
) -> float:
    """The sender's time rebuilt from its ``secMark`` and our receive time ``t_rx``.

    The result is ``minute + secMark/1000`` for the latest UTC minute such that it is not
    after ``t_rx + tolerance_s``, then clamped to ``t_rx`` (a sender clock slightly ahead
    reads as age 0, not as a minute-old message). Leap-second values 60000..60999 count
    as the minute's last instant; reserved values and 65535 (unavailable) give ``t_rx``.
    """
    if sec_mark_ms >= 60000:
        if sec_mark_ms >= 61000:
            return t_rx
        sec_mark_ms = 59999
    base = math.floor(t_rx / 60.0) * 60.0
    t = base + sec_mark_ms / 1000.0
    if t > t_rx + tolerance_s:
        t -= 60.0
    return min(t, t_rx)


def enu_heading_to_j2735(heading_rad: float) -> int:
    """ENU heading (radians, 0 = east, CCW) -> J2735 Heading (0.0125 degree, from north, CW)."""
    if not math.isfinite(heading_rad):
        return j.HEADING_UNAVAILABLE
    compass = (90.0 - math.degrees(heading_rad)) % 360.0
    # round() can reach 28800 (= 360 degrees) from just below 360: that is north, code 0.
    return round(compass / j.HEADING_UNIT) % 28800


def j2735_heading_to_enu(code: int) -> float:
    """J2735 Heading code -> ENU heading, radians in [-π, π) (NaN when unavailable)."""
    if code == j.HEADING_UNAVAILABLE:
        return math.nan
    return wrap_angle(math.radians(90.0 - code * j.HEADING_UNIT))


def state_to_core(
    state: VehicleState,
    origin: Origin,
    temp_id: bytes,
    msg_cnt: int,
    *,
    alt_m: float | None = None,
) -> j.BsmCore:
    """Build the BSM core for ``state`` (ENU around ``origin``) as sender ``temp_id``.

    ``secMark`` comes from ``state.t`` (J2735: the time the position was determined).
    ``alt_m``, metres above the ellipsoid, defaults to the height of the ENU point (the
    vehicle on the local tangent plane). Negative speed (reversing) is sent as its
    magnitude with transmission ``reverseGears``. Unknown length/width (0) stay 0; the
    steering angle and lateral/vertical acceleration are sent as unavailable.
    """
    lat, lon, alt = enu_to_geodetic(origin, state.x, state.y, 0.0)
    # J2735 longitude spans (-180, 180]: -180 degrees is the same meridian as +180, which
    # is representable; values past ±180 (an origin near the antimeridian) are normalized
    # to that span too. This is the angle's periodicity, not wrapping an out-of-range value.
    lon = 180.0 - (180.0 - lon) % 360.0
    if math.isfinite(lon) and round(lon / j.LATLON_UNIT) < j.LON_MIN:
        lon += 360.0  # rounds onto -180 degrees: send the same meridian as +180
    if alt_m is not None:
        alt = alt_m
    reversing = state.speed < 0.0
    return j.BsmCore(
        msg_cnt=msg_cnt % (j.MSG_CNT_MAX + 1),
        temp_id=temp_id,
        sec_mark=sec_mark(state.t),
        lat=_quantize_or(lat, j.LATLON_UNIT, j.LAT_MIN, j.LAT_MAX, j.LAT_UNAVAILABLE),
        lon=_quantize_or(lon, j.LATLON_UNIT, j.LON_MIN, j.LON_MAX, j.LON_UNAVAILABLE),
        elev=_quantize_or(alt, j.ELEV_UNIT, j.ELEV_MIN, j.ELEV_MAX, j.ELEV_UNAVAILABLE),
        transmission="reverseGears" if reversing else "forwardGears",
        speed=_quantize_or(abs(state.speed), j.SPEED_UNIT, 0, j.SPEED_MAX, j.SPEED_UNAVAILABLE),
        heading=enu_heading_to_j2735(state.heading),
        accel_long=_quantize_or(
            state.accel, j.ACCEL_UNIT, j.ACCEL_MIN, j.ACCEL_MAX, j.ACCEL_UNAVAILABLE
        ),
        # J2735 yaw rate is clockwise positive, ours counter-clockwise; it has no
        # "unavailable" code, so unknown is sent as 0.
        yaw_rate=_quantize_or(
            -math.degrees(state.yaw_rate), j.YAW_RATE_UNIT, j.YAW_RATE_MIN, j.YAW_RATE_MAX, 0
        ),
        width=_quantize_or(state.width, j.SIZE_UNIT, 0, j.WIDTH_MAX, 0),
        length=_quantize_or(state.length, j.SIZE_UNIT, 0, j.LENGTH_MAX, 0),
    )


def core_to_state(core: j.BsmCore, origin: Origin, vehicle_id: int, t_send: float) -> VehicleState:
    """The ``VehicleState`` a BSM core describes, in the ENU frame around ``origin``.

    ``t_send`` is the sender's time (see ``reconstruct_send_time``). Unavailable position,
    speed or heading become NaN; unavailable acceleration 0; ``reverseGears`` makes the
    speed negative.
    """
    if core.lat == j.LAT_UNAVAILABLE or core.lon == j.LON_UNAVAILABLE:
        x = y = math.nan
    else:
        alt = None if core.elev == j.ELEV_UNAVAILABLE else core.elev * j.ELEV_UNIT
        x, y, _ = geodetic_to_enu(origin, core.lat * j.LATLON_UNIT, core.lon * j.LATLON_UNIT, alt)
    if core.speed == j.SPEED_UNAVAILABLE:
        speed = math.nan
    else:
        speed = core.speed * j.SPEED_UNIT
        if core.transmission == "reverseGears":
            speed = -speed
    accel = 0.0 if core.accel_long == j.ACCEL_UNAVAILABLE else core.accel_long * j.ACCEL_UNIT
    return VehicleState(
        vehicle_id=vehicle_id,
        t=t_send,
        x=float(x),
        y=float(y),
        speed=speed,
        heading=j2735_heading_to_enu(core.heading),
        accel=accel,
        yaw_rate=-math.radians(core.yaw_rate * j.YAW_RATE_UNIT),
        length=core.length * j.SIZE_UNIT,
        width=core.width * j.SIZE_UNIT,
    )
