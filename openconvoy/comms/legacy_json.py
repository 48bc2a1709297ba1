"""The original OpenConvoy implementation's V2V wire format, for mixed fleets.

One UTF-8 JSON object per UDP datagram, sent to IPv4 multicast 224.0.0.1:5004 with TTL 1.
Field names are the original's; units as documented by it where known:

==========================  ==========================================================
``time``                    sender's time of the state, seconds (Unix time)
``latitude``, ``longitude`` WGS-84 degrees
``elevation``               metres above the ellipsoid
``position_accuracy``       metres (null: unknown)
``speed``                   m/s (negative when reversing)
``heading``                 compass degrees: 0 = north, clockwise
``acceleration``            longitudinal, m/s²
``yaw_rate``                degrees/s, clockwise positive (the compass convention of
                            ``heading``; an assumption: the original does not say)
``steering_wheel_angle``    degrees (null: unknown)
``transmission_state``      J2735 TransmissionState name, e.g. "forwardGears"
``brake_system_status``     null (unknown) or whatever the sender put there
``vehicle_length``,         metres
``vehicle_width``
``path_history``,           carried through, not interpreted ([] / null when we send)
``path_prediction``,
``exterior_lights``
``event_flags``             ``{"car": convoy position (0 = leader), "abort": bool}``
==========================  ==========================================================

``event_flags.abort`` is the convoy-wide abort. An operator's abort (``make_abort``) uses
``car = -1`` (no convoy position) and carries no position (latitude/longitude null).

Parsing is strict about what the convoy needs (``time``, ``latitude``, ``longitude``,
``speed``, ``heading``, ``event_flags.car``: finite numbers / an integer) and lenient about
the rest (missing optional fields default, unknown fields are ignored), and raises
``CompatDecodeError`` for anything else. No I/O here: ``multicast`` moves the bytes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from openconvoy.comms.geodesy import Origin, enu_to_geodetic, geodetic_to_enu
from openconvoy.core.state import VehicleState, wrap_angle

COMPAT_GROUP = "224.0.0.1"
COMPAT_PORT = 5004
COMPAT_TTL = 1

#: ``event_flags.car`` of a message sent by an operator (not a convoy member).
OPERATOR_CAR = -1

FIELDS = (
    "time",
    "latitude",
    "longitude",
    "elevation",
    "position_accuracy",
    "speed",
    "heading",
    "acceleration",
    "yaw_rate",
    "steering_wheel_angle",
    "transmission_state",
    "brake_system_status",
    "vehicle_length",
    "vehicle_width",
    "path_history",
    "path_prediction",
    "exterior_lights",
    "event_flags",
)

# A legitimate message is well under 1 kB; refuse to parse anything absurd.
MAX_MESSAGE_BYTES = 65_507


class CompatDecodeError(ValueError):
    """The bytes are not a valid compatibility-format message (message says why)."""


@dataclass(frozen=True, slots=True)
class CompatMessage:
    """A parsed compatibility message.

    Attributes:
        car: sender's convoy position (0 = leader; -1 = an operator, not a vehicle).
        abort: the convoy-wide abort flag.
        t: the sender's time, seconds.
        lat_deg, lon_deg: position, degrees (None for a position-less abort).
        elevation_m: metres above the ellipsoid (None when absent).
        speed, heading_deg, acceleration, yaw_rate_dps, length_m, width_m: as sent
            (heading in compass degrees; 0.0 where an optional field is absent).
        raw: the whole decoded JSON object, for fields carried through.
    """

    car: int
    abort: bool
    t: float
    lat_deg: float | None
    lon_deg: float | None
    elevation_m: float | None
    speed: float
    heading_deg: float
    acceleration: float = 0.0
    yaw_rate_dps: float = 0.0
    length_m: float = 0.0
    width_m: float = 0.0
    raw: dict[str, Any] | None = None


def enu_heading_to_compass_deg(heading_rad: float) -> float:
    """ENU heading (radians, 0 = east, CCW) -> compass degrees in [0, 360) (0 = north, CW)."""
    return (90.0 - math.degrees(heading_rad)) % 360.0


def compass_deg_to_enu_heading(compass_deg: float) -> float:
    """Compass degrees (0 = north, CW) -> ENU heading, radians in [-π, π)."""
    return wrap_angle(math.radians(90.0 - compass_deg))


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def encode_state(
    state: VehicleState, origin: Origin, *, abort: bool = False, car: int | None = None
) -> bytes:
    """The compatibility-format datagram for ``state`` (ENU around ``origin``).

    ``car`` defaults to ``state.vehicle_id``. NaN fields are sent as null (JSON has no NaN).
    """
    lat, lon, alt = enu_to_geodetic(origin, state.x, state.y, 0.0)
    msg: dict[str, Any] = {
        "time": state.t,
        "latitude": _finite(lat),
        "longitude": _finite(lon),
        "elevation": _finite(alt),
        "position_accuracy": None,
        "speed": _finite(state.speed),
        "heading": _finite(enu_heading_to_compass_deg(state.heading))
        if math.isfinite(state.heading)
        else None,
        "acceleration": _finite(state.accel),
        "yaw_rate": _finite(-math.degrees(state.yaw_rate)),
        "steering_wheel_angle": None,
        "transmission_state": "reverseGears" if state.speed < 0 else "forwardGears",
        "brake_system_status": None,
        "vehicle_length": state.length,
        "vehicle_width": state.width,
        "path_history": [],
        "path_prediction": None,
        "exterior_lights": None,
        "event_flags": {"car": state.vehicle_id if car is None else car, "abort": bool(abort)},
    }
    return json.dumps(msg, allow_nan=False, separators=(",", ":")).encode()


def make_abort(t: float, car: int = OPERATOR_CAR) -> bytes:
    """An abort datagram from ``car`` (default: an operator) at time ``t``, no position."""
    msg: dict[str, Any] = {name: None for name in FIELDS}
    msg.update(
        time=t,
        speed=0.0,
        heading=0.0,
        path_history=[],
        event_flags={"car": car, "abort": True},
    )
    return json.dumps(msg, allow_nan=False, separators=(",", ":")).encode()


def _number(obj: dict[str, Any], key: str, *, required: bool) -> float | None:
    v = obj.get(key)
    if v is None:
        if required:
            raise CompatDecodeError(f"field {key!r} missing or null")
        return None
    # bool is an int in Python but not a number on the wire
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CompatDecodeError(f"field {key!r} is not a number: {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise CompatDecodeError(f"field {key!r} is not finite")
    return v


def decode(data: bytes) -> CompatMessage:
    """Parse one compatibility datagram; raise ``CompatDecodeError`` if it is not valid."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise CompatDecodeError(f"message of {len(data)} bytes is too long")
    try:
        obj = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise CompatDecodeError(f"not UTF-8 JSON: {type(exc).__name__}") from None
    if not isinstance(obj, dict):
        raise CompatDecodeError("JSON value is not an object")
    flags = obj.get("event_flags")
    if not isinstance(flags, dict):
        raise CompatDecodeError("event_flags missing or not an object")
    car = flags.get("car")
    if isinstance(car, bool) or not isinstance(car, int):
        raise CompatDecodeError(f"event_flags.car is not an integer: {car!r}")
    abort = flags.get("abort", False)
    if not isinstance(abort, bool):
        raise CompatDecodeError(f"event_flags.abort is not a boolean: {abort!r}")
    t = _number(obj, "time", required=True)
    assert t is not None  # required: _number raised otherwise
    # an abort needs no position; a state message does
    lat = _number(obj, "latitude", required=not abort)
    lon = _number(obj, "longitude", required=not abort)
    if (lat is None) != (lon is None):
        raise CompatDecodeError("latitude and longitude must both be given")
    if (
        lat is not None
        and lon is not None
        and not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0)
    ):
        raise CompatDecodeError(f"position out of range: {lat}, {lon}")
    speed = _number(obj, "speed", required=not abort)
    heading = _number(obj, "heading", required=not abort)
    return CompatMessage(
        car=car,
        abort=abort,
        t=t,
        lat_deg=lat,
        lon_deg=lon,
        elevation_m=_number(obj, "elevation", required=False),
        speed=speed or 0.0,
        heading_deg=heading or 0.0,
        acceleration=_number(obj, "acceleration", required=False) or 0.0,
        yaw_rate_dps=_number(obj, "yaw_rate", required=False) or 0.0,
        length_m=_number(obj, "vehicle_length", required=False) or 0.0,
        width_m=_number(obj, "vehicle_width", required=False) or 0.0,
        raw=obj,
    )


def to_state(msg: CompatMessage, origin: Origin, vehicle_id: int | None = None) -> VehicleState:
    """The ``VehicleState`` of a message with a position (``ValueError`` for an abort
    without one). ``vehicle_id`` defaults to ``msg.car``; ``t`` is the sender's time."""
    if msg.lat_deg is None or msg.lon_deg is None:
        raise ValueError("compatibility message carries no position")
    x, y, _ = geodetic_to_enu(origin, msg.lat_deg, msg.lon_deg, msg.elevation_m)
    return VehicleState(
        vehicle_id=msg.car if vehicle_id is None else vehicle_id,
        t=msg.t,
        x=float(x),
        y=float(y),
        speed=msg.speed,
        heading=compass_deg_to_enu_heading(msg.heading_deg),
        accel=msg.acceleration,
        yaw_rate=-math.radians(msg.yaw_rate_dps),
        length=msg.length_m,
        width=msg.width_m,
    )
