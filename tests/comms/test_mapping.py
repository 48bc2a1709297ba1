"""State <-> BSM mapping: units, heading convention, clamping, time, exact round trips."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms import bsm as j
from openconvoy.comms.bsm import decode_frame, encode_frame
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.comms.mapping import (
    core_to_state,
    enu_heading_to_j2735,
    j2735_heading_to_enu,
    reconstruct_send_time,
    sec_mark,
    state_to_core,
)
from openconvoy.core.state import VehicleState

ORIGIN = Origin(47.3977, 8.5456, 488.0)
TID = b"\xde\xad\xbe\xef"


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@pytest.mark.parametrize(
    "enu_deg,compass_deg",
    [(0, 90), (90, 0), (180, 270), (-90, 180), (45, 45), (135, 315), (360, 90), (-0.001, 90.001)],
)
def test_heading_conversion(enu_deg, compass_deg):
    code = enu_heading_to_j2735(math.radians(enu_deg))
    assert code == round(compass_deg / 0.0125) % 28800
    back = j2735_heading_to_enu(code)
    assert _angle_diff(back, math.radians(enu_deg)) <= math.radians(0.0125 / 2) + 1e-12
    assert -math.pi <= back < math.pi


def test_heading_just_below_north_rounds_to_zero_not_28800():
    # compass 359.999 degrees rounds to 360.0000 = code 28800, which means "unavailable"
    assert enu_heading_to_j2735(math.radians(90.0 + 0.001)) == 0
    assert j2735_heading_to_enu(j.HEADING_UNAVAILABLE) != j2735_heading_to_enu(0)
    assert math.isnan(j2735_heading_to_enu(j.HEADING_UNAVAILABLE))


def test_sec_mark_is_ms_within_minute():
    assert sec_mark(0.0) == 0
    assert sec_mark(59.9999) == 59999
    assert sec_mark(60.0) == 0
    assert sec_mark(1_700_000_012.3456) == 32345  # 1_700_000_000 is minute + 20 s
    assert sec_mark(-0.5) == 59500


@pytest.mark.parametrize(
    "t_send,t_rx",
    [
        (1000.000, 1000.080),  # usual: 80 ms old
        (1019.990, 1020.050),  # sent before the minute boundary, received after
        (1019.990, 1078.900),  # 58.9 s old: the right minute (60 s less the tolerance)
        (1020.100, 1020.000),  # sender's clock 100 ms ahead: age 0, not 60 s
    ],
)
def test_reconstructed_send_time(t_send, t_rx):
    t = reconstruct_send_time(sec_mark(t_send), t_rx)
    assert t <= t_rx  # age never negative
    if t_send <= t_rx:
        assert t == pytest.approx(t_send, abs=1e-3)
    else:
        assert t == t_rx


def test_reconstruct_special_sec_marks():
    assert reconstruct_send_time(65535, 1234.5) == 1234.5  # unavailable
    assert reconstruct_send_time(60500, 1261.0) == pytest.approx(1259.999)  # leap second
    # beyond the tolerance a "future" secMark is read as last minute's
    assert reconstruct_send_time(sec_mark(1001.5), 1000.0) == pytest.approx(941.5)


def test_clamps_never_wraps():
    s = VehicleState(
        0, 0.0, 0.0, 0.0, speed=500.0, heading=0.0, accel=-50.0, yaw_rate=-100.0,
        length=99.0, width=-1.0,
    )  # fmt: skip
    core = state_to_core(s, ORIGIN, TID, msg_cnt=130)
    assert core.msg_cnt == 2  # msgCnt is a counter: it wraps
    assert core.speed == j.SPEED_MAX  # 163.8 m/s or more
    assert core.accel_long == j.ACCEL_MIN
    assert core.yaw_rate == j.YAW_RATE_MAX  # -100 rad/s CCW = far over +327.67 deg/s CW
    assert core.length == j.LENGTH_MAX and core.width == 0
    far = Origin(89.99, 0.0, 0.0)
    north = state_to_core(VehicleState(0, 0.0, 0.0, 5000.0, 0.0, 0.0), far, TID, 0)
    assert north.lat <= j.LAT_MAX
    high = state_to_core(VehicleState(0, 0.0, 0.0, 0.0, 0.0, 0.0), Origin(0, 0, 9000.0), TID, 0)
    assert high.elev == j.ELEV_MAX
    deep = state_to_core(VehicleState(0, 0.0, 0.0, 0.0, 0.0, 0.0), Origin(0, 0, -500.0), TID, 0)
    assert deep.elev == j.ELEV_MIN


def test_reverse_speed_uses_reverse_gears():
    s = VehicleState(1, 10.0, 3.0, 4.0, speed=-1.5, heading=1.0)
    core = state_to_core(s, ORIGIN, TID, 0)
    assert core.transmission == "reverseGears" and core.speed == 75
    assert core_to_state(core, ORIGIN, 1, 10.0).speed == pytest.approx(-1.5)


def test_nan_fields_are_sent_as_unavailable():
    s = VehicleState(0, 0.0, math.nan, 0.0, speed=math.nan, heading=math.nan, accel=math.nan)
    core = state_to_core(s, ORIGIN, TID, 0)
    assert core.lat == j.LAT_UNAVAILABLE and core.lon == j.LON_UNAVAILABLE
    assert core.speed == j.SPEED_UNAVAILABLE and core.heading == j.HEADING_UNAVAILABLE
    assert core.accel_long == j.ACCEL_UNAVAILABLE
    back = core_to_state(decode_frame(encode_frame(core)).core, ORIGIN, 0, 0.0)
    assert math.isnan(back.x) and math.isnan(back.speed) and math.isnan(back.heading)


def test_known_position_maps_to_expected_lat_lon():
    s = VehicleState(0, 0.0, x=100.0, y=-50.0, speed=2.0, heading=0.5)
    core = state_to_core(s, ORIGIN, TID, 0)
    lat, lon, alt = enu_to_geodetic(ORIGIN, 100.0, -50.0)
    assert core.lat == round(lat * 1e7) and core.lon == round(lon * 1e7)
    assert core.elev == round(alt * 10) == 4880


def _pos_tol_m(alt_m: float, distance_m: float) -> float:
    """J2735 position resolution, metres, for a point ``distance_m`` from the origin.

    Half a unit of latitude/longitude (0.5e-7 degree) on the largest WGS-84 radius of
    curvature (6,399,594 m at the poles, plus the height; ~5.6 mm), plus the tilt of
    half an elevation unit (0.05 m) between the local vertical there and the origin's.
    """
    half_latlon = math.radians(0.5e-7) * (6_399_594 + alt_m + 100.0)
    return half_latlon + 0.05 * distance_m / 6_350_000 + 1e-6


@settings(max_examples=300, deadline=None)
@given(
    lat0=st.floats(-85.0, 85.0),
    lon0=st.floats(-180.0, 180.0),
    alt0=st.floats(-400.0, 6000.0),
    x=st.floats(-20_000.0, 20_000.0),
    y=st.floats(-20_000.0, 20_000.0),
    speed=st.floats(-163.8, 163.8),
    heading=st.floats(-10.0, 10.0),
    accel=st.floats(-20.0, 20.0),
    yaw_rate=st.floats(-5.7, 5.7),  # 327.67 degree/s
    length=st.floats(0.0, 40.95),
    width=st.floats(0.0, 10.23),
    t=st.floats(0.0, 2e9),
    age=st.floats(0.0, 30.0),
    msg_cnt=st.integers(0, 10_000),
)
def test_state_to_bytes_to_state_exact_to_resolution(
    lat0, lon0, alt0, x, y, speed, heading, accel, yaw_rate, length, width, t, age, msg_cnt
):
    origin = Origin(lat0, lon0, alt0)
    s = VehicleState(3, t, x, y, speed, heading, accel, yaw_rate, length, width)
    data = encode_frame(state_to_core(s, origin, TID, msg_cnt))
    decoded = decode_frame(data).core
    assert decoded.msg_cnt == msg_cnt % 128 and decoded.temp_id == TID
    t_rx = t + age
    back = core_to_state(decoded, origin, 3, reconstruct_send_time(decoded.sec_mark, t_rx))
    tol = _pos_tol_m(alt0, math.hypot(x, y))
    assert abs(back.x - x) <= tol and abs(back.y - y) <= tol
    assert abs(back.speed - speed) <= 0.01 + 1e-9
    assert _angle_diff(back.heading, heading) <= math.radians(0.0125 / 2) + 1e-9
    assert abs(back.accel - accel) <= 0.005 + 1e-9
    assert abs(back.yaw_rate - yaw_rate) <= math.radians(0.005) + 1e-9
    assert abs(back.length - length) <= 0.005 + 1e-9
    assert abs(back.width - width) <= 0.005 + 1e-9
    # secMark has 1 ms resolution and truncates: t - 1 ms < t' <= t (float slack for 2e9 s)
    assert t - 1e-3 - 1e-6 <= back.t <= t + 1e-6
    assert back.vehicle_id == 3


@pytest.mark.parametrize("lon0", [-180.0, 180.0, 179.99999])
def test_antimeridian_longitude_is_normalized_not_clamped(lon0):
    origin = Origin(10.0, lon0, 0.0)
    # 0.004 m east of 180 degrees rounds onto -180, which J2735 cannot carry: +180 is sent.
    for x in (-3.0, 0.0, 0.00390625, 3.0):
        core = state_to_core(VehicleState(0, 0.0, x, 1.0, 0.0, 0.0), origin, TID, 0)
        back = core_to_state(decode_frame(encode_frame(core)).core, origin, 0, 0.0)
        assert back.x == pytest.approx(x, abs=6e-3) and back.y == pytest.approx(1.0, abs=6e-3)
