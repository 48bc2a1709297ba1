"""Geodetic (WGS-84 latitude, longitude, altitude) <-> local ENU around a convoy origin.

The local frame of DESIGN.md's conventions is East-North-Up, metres, tangent to the
ellipsoid at the convoy origin. The conversions delegate to pymap3d (a maintained
geodesy library), never hand-written ellipsoid math. MAVLink speaks NED, hence the small
NED helpers. Every function accepts Python floats or numpy arrays (broadcast together)
and returns the same kind.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import numpy as np
import pymap3d

from openconvoy.core.errors import ConfigError

#: A float or a numpy array of floats; functions return the same kind they were given.
Num = float | np.ndarray

# Built once: pymap3d otherwise rebuilds the WGS-84 ellipsoid on every call, which
# triples the cost of a scalar conversion (the receiver does one per message).
_WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


@dataclass(frozen=True, slots=True)
class Origin:
    """The convoy origin: geodetic point where the local ENU frame is tangent.

    Attributes:
        lat_deg: WGS-84 latitude, degrees (north positive).
        lon_deg: WGS-84 longitude, degrees (east positive).
        alt_m: height above the WGS-84 ellipsoid, metres.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        if not -90.0 <= self.lat_deg <= 90.0:
            raise ConfigError(f"origin latitude must be in [-90, 90] degrees, got {self.lat_deg}")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ConfigError(
                f"origin longitude must be in [-180, 180] degrees, got {self.lon_deg}"
            )


def _out(v: Num) -> Num:
    # pymap3d returns numpy scalars (or 0-d arrays) for scalar input; hand back plain floats
    # so callers comparing, formatting or JSON-encoding them need no special case.
    a = np.asarray(v)
    return float(a) if a.ndim == 0 else a


@overload
def enu_to_geodetic(
    origin: Origin, x: float, y: float, z: float = 0.0
) -> tuple[float, float, float]: ...
@overload
def enu_to_geodetic(
    origin: Origin, x: np.ndarray, y: Num, z: Num = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
def enu_to_geodetic(origin: Origin, x: Num, y: Num, z: Num = 0.0) -> tuple[Num, Num, Num]:
    """Local ENU (metres east, north, up of ``origin``) -> (lat_deg, lon_deg, alt_m)."""
    lat, lon, alt = pymap3d.enu2geodetic(
        x, y, z, origin.lat_deg, origin.lon_deg, origin.alt_m, ell=_WGS84, deg=True
    )
    return _out(lat), _out(lon), _out(alt)


@overload
def geodetic_to_enu(
    origin: Origin, lat_deg: float, lon_deg: float, alt_m: float | None = None
) -> tuple[float, float, float]: ...
@overload
def geodetic_to_enu(
    origin: Origin, lat_deg: np.ndarray, lon_deg: Num, alt_m: Num | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
def geodetic_to_enu(
    origin: Origin, lat_deg: Num, lon_deg: Num, alt_m: Num | None = None
) -> tuple[Num, Num, Num]:
    """(lat_deg, lon_deg, alt_m) -> local ENU (x east, y north, z up), metres.

    ``alt_m`` defaults to the origin's altitude (z = 0 then, for points on the same
    height), convenient when a source (a BSM with elevation unavailable) has no altitude.
    """
    if alt_m is None:
        alt_m = origin.alt_m
    x, y, z = pymap3d.geodetic2enu(
        lat_deg, lon_deg, alt_m, origin.lat_deg, origin.lon_deg, origin.alt_m, ell=_WGS84, deg=True
    )
    return _out(x), _out(y), _out(z)


def ned_to_enu(north: Num, east: Num, down: Num) -> tuple[Num, Num, Num]:
    """NED vector components (metres or m/s) -> ENU (east, north, up)."""
    return east, north, -down


def enu_to_ned(east: Num, north: Num, up: Num) -> tuple[Num, Num, Num]:
    """ENU vector components -> NED (north, east, down)."""
    return north, east, -up


def ned_yaw_to_enu_heading(yaw_rad: Num) -> Num:
    """NED yaw (radians, 0 = north, clockwise) -> ENU heading (radians, 0 = east, CCW).

    Not wrapped: the result is π/2 - yaw; wrap with ``core.state.wrap_angle`` if needed.
    The map is its own inverse.
    """
    return np.pi / 2 - yaw_rad


def enu_heading_to_ned_yaw(heading_rad: Num) -> Num:
    """ENU heading (radians, 0 = east, CCW) -> NED yaw (radians, 0 = north, clockwise)."""
    return np.pi / 2 - heading_rad
