import math

import numpy as np
import pytest

from openconvoy.comms.geodesy import (
    Origin,
    enu_heading_to_ned_yaw,
    enu_to_geodetic,
    enu_to_ned,
    geodetic_to_enu,
    ned_to_enu,
    ned_yaw_to_enu_heading,
)

ORIGIN = Origin(47.3977, 8.5456, 488.0)  # PX4 SITL's default home


def test_origin_maps_to_zero():
    assert enu_to_geodetic(ORIGIN, 0.0, 0.0) == pytest.approx((47.3977, 8.5456, 488.0))
    x, y, z = geodetic_to_enu(ORIGIN, 47.3977, 8.5456, 488.0)
    assert (x, y, z) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert isinstance(x, float)


def test_north_and_east_displacements_match_wgs84_radii():
    # 100 m north: arc on the meridional radius of curvature M (+ the origin height)
    lat, lon, _ = enu_to_geodetic(ORIGIN, 0.0, 100.0)
    lat0 = math.radians(ORIGIN.lat_deg)
    a, e2 = 6378137.0, 6.69437999014e-3
    m = a * (1 - e2) / (1 - e2 * math.sin(lat0) ** 2) ** 1.5
    n = a / math.sqrt(1 - e2 * math.sin(lat0) ** 2)
    assert lat - ORIGIN.lat_deg == pytest.approx(math.degrees(100.0 / (m + ORIGIN.alt_m)), rel=1e-6)
    assert lon == pytest.approx(ORIGIN.lon_deg, abs=1e-12)
    lat, lon, _ = enu_to_geodetic(ORIGIN, 100.0, 0.0)
    assert lon - ORIGIN.lon_deg == pytest.approx(
        math.degrees(100.0 / ((n + ORIGIN.alt_m) * math.cos(lat0))), rel=1e-6
    )


def test_round_trip_arrays():
    rng = np.random.default_rng(1)
    x, y, z = rng.uniform(-5000, 5000, (3, 1000))
    lat, lon, alt = enu_to_geodetic(ORIGIN, x, y, z)
    assert isinstance(lat, np.ndarray) and lat.shape == (1000,)
    x2, y2, z2 = geodetic_to_enu(ORIGIN, lat, lon, alt)
    np.testing.assert_allclose(x2, x, atol=1e-6)
    np.testing.assert_allclose(y2, y, atol=1e-6)
    np.testing.assert_allclose(z2, z, atol=1e-6)


def test_default_altitude_is_origins():
    lat, lon, _ = enu_to_geodetic(ORIGIN, 30.0, -20.0)
    x, y, z = geodetic_to_enu(ORIGIN, lat, lon)
    assert (x, y) == pytest.approx((30.0, -20.0), abs=1e-6)
    # The tangent plane drops away from the ellipsoid: 36 m off the origin that is ~0.1 mm
    assert abs(z) < 1e-3


def test_origin_validates():
    with pytest.raises(ValueError, match="latitude"):
        Origin(91.0, 0.0)
    with pytest.raises(ValueError, match="longitude"):
        Origin(0.0, 181.0)


def test_ned_helpers():
    assert ned_to_enu(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)
    assert enu_to_ned(2.0, 1.0, -3.0) == (1.0, 2.0, 3.0)
    assert ned_yaw_to_enu_heading(0.0) == pytest.approx(math.pi / 2)  # north
    assert ned_yaw_to_enu_heading(math.pi / 2) == pytest.approx(0.0)  # east
    assert enu_heading_to_ned_yaw(math.pi) == pytest.approx(-math.pi / 2)  # west
    yaw = np.array([0.0, 1.0])
    np.testing.assert_allclose(ned_yaw_to_enu_heading(yaw), [math.pi / 2, math.pi / 2 - 1.0])
