"""The original implementation's JSON format: field names, units, round trips, rejection."""

from __future__ import annotations

import json
import math

import pytest

from openconvoy.comms import legacy_json as compat
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 12.0)


def test_wire_format_fields_and_units():
    s = VehicleState(2, 1_700_000_000.25, 30.0, -40.0, 1.5, math.radians(90.0), 0.3, 0.1, 0.5, 0.3)
    obj = json.loads(compat.encode_state(s, ORIGIN))
    assert set(obj) == set(compat.FIELDS)
    lat, lon, _ = enu_to_geodetic(ORIGIN, 30.0, -40.0)
    assert obj["time"] == 1_700_000_000.25
    assert obj["latitude"] == pytest.approx(lat, abs=1e-12)
    assert obj["longitude"] == pytest.approx(lon, abs=1e-12)
    assert obj["speed"] == 1.5
    assert obj["heading"] == pytest.approx(0.0)  # ENU north = compass 0
    assert obj["yaw_rate"] == pytest.approx(-math.degrees(0.1))  # clockwise positive
    assert obj["acceleration"] == 0.3
    assert obj["vehicle_length"] == 0.5 and obj["vehicle_width"] == 0.3
    assert obj["event_flags"] == {"car": 2, "abort": False}
    assert obj["transmission_state"] == "forwardGears"


@pytest.mark.parametrize("enu_deg,compass", [(0, 90), (90, 0), (180, 270), (-90, 180), (-45, 135)])
def test_heading_compass_conversion(enu_deg, compass):
    assert compat.enu_heading_to_compass_deg(math.radians(enu_deg)) == pytest.approx(compass)
    back = compat.compass_deg_to_enu_heading(compass)
    assert abs((back - math.radians(enu_deg) + math.pi) % (2 * math.pi) - math.pi) < 1e-12


def test_round_trip_with_state():
    s = VehicleState(1, 1234.5, -120.25, 77.5, -0.75, -2.0, -1.25, 0.2, 0.55, 0.29)
    msg = compat.decode(compat.encode_state(s, ORIGIN))
    assert msg.car == 1 and msg.abort is False
    back = compat.to_state(msg, ORIGIN)
    assert back.vehicle_id == 1 and back.t == 1234.5
    for name in ("x", "y"):
        assert getattr(back, name) == pytest.approx(getattr(s, name), abs=1e-6)
    for name in ("speed", "accel", "yaw_rate", "length", "width"):
        assert getattr(back, name) == pytest.approx(getattr(s, name), abs=1e-12)
    assert back.heading == pytest.approx(s.heading, abs=1e-12)


def test_abort_messages():
    msg = compat.decode(compat.make_abort(99.0))
    assert msg.abort and msg.car == compat.OPERATOR_CAR and msg.lat_deg is None
    with pytest.raises(ValueError, match="no position"):
        compat.to_state(msg, ORIGIN)
    s = VehicleState(0, 5.0, 1.0, 2.0, 1.0, 0.0)
    msg = compat.decode(compat.encode_state(s, ORIGIN, abort=True))
    assert msg.abort and msg.car == 0 and compat.to_state(msg, ORIGIN).x == pytest.approx(1.0)


def test_lenient_about_optional_and_unknown_fields():
    data = json.dumps(
        {
            "time": 1.0,
            "latitude": 28.6024,
            "longitude": -81.2001,
            "speed": 2,
            "heading": 270,
            "event_flags": {"car": 1},
            "some_future_field": [1, 2, 3],
        }
    ).encode()
    msg = compat.decode(data)
    assert msg.abort is False and msg.speed == 2.0 and msg.elevation_m is None
    s = compat.to_state(msg, ORIGIN)
    assert s.heading == pytest.approx(math.pi) or s.heading == pytest.approx(-math.pi)
    assert abs(s.x) < 1e-6 and abs(s.y) < 1e-6


@pytest.mark.parametrize(
    "data,why",
    [
        (b"\xff\xfe{", "UTF-8"),
        (b"{not json", "JSON"),
        (b"[1, 2]", "not an object"),
        (b'{"time": 1, "latitude": 1, "longitude": 1, "speed": 1, "heading": 1}', "event_flags"),
        (b'{"time": 1, "latitude": 1, "longitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": "0"}}', "car"),
        (b'{"time": 1, "latitude": 1, "longitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": true}}', "car"),
        (b'{"time": 1, "latitude": 1, "longitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": 0, "abort": "yes"}}', "abort"),
        (b'{"time": 1, "latitude": 91, "longitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": 0}}', "out of range"),
        (b'{"time": NaN, "latitude": 1, "longitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": 0}}', "finite"),
        (b'{"time": 1, "latitude": 1, "speed": 1, "heading": 1,'
         b' "event_flags": {"car": 0}}', "longitude"),
        (b'{"time": 1, "latitude": 1, "longitude": 1, "speed": "fast", "heading": 1,'
         b' "event_flags": {"car": 0}}', "speed"),
        (b"[" * 60_000, "JSON"),  # deep nesting: RecursionError inside json
        (b" " * 70_000, "too long"),
    ],
)  # fmt: skip
def test_rejects_invalid(data, why):
    with pytest.raises(compat.CompatDecodeError, match=why):
        compat.decode(data)
