"""SAE J2735 Basic Safety Message codec: MessageFrame (messageId 20) <-> ``BsmCore``.

The wire format is UPER (X.691 unaligned PER) of a J2735 ``MessageFrame`` whose value is a
``BasicSafetyMessage``; a bare BSM is never sent. The ASN.1 module is ``j2735.asn`` next to
this file (the project's own restatement of the types the core needs), compiled once per
process by ``asn1tools``. Part II contents, regional extensions and later-edition extension
additions are open types there, so they are skipped on decode, never rejected. Two layers
are read and written here directly, for speed, and held equal to asn1tools by the tests:
the MessageFrame's header and open-type length, and on decode the fixed 290-bit core of a
core-only BSM (what convoy members send); asn1tools does the BSM encoding and decodes
every other BSM.

``BsmCore`` holds the core (Part I) in J2735 integer units; ``to_physical`` turns it into SI
and degrees. This module knows nothing of the convoy's local frame: ``mapping`` does that.
"""

from __future__ import annotations

import functools
import operator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from openconvoy.core.errors import DependencyMissing

#: messageId of a BasicSafetyMessage in a MessageFrame.
BSM_MESSAGE_ID = 20
#: Every BSM MessageFrame starts with these two octets (extension bit 0, messageId 20).
BSM_FRAME_PREFIX = b"\x00\x14"

# J2735 ranges and special values (the DE_* definitions; units in the comments).
MSG_CNT_MAX = 127  # MsgCount, wraps 127 -> 0
SEC_MARK_MAX = 65535  # DSecond, ms within the minute
SEC_MARK_UNAVAILABLE = 65535
LAT_MIN, LAT_MAX = -900000000, 900000000  # Latitude, 1e-7 degree
LAT_UNAVAILABLE = 900000001
LON_MIN, LON_MAX = -1799999999, 1800000000  # Longitude, 1e-7 degree
LON_UNAVAILABLE = 1800000001
ELEV_MIN, ELEV_MAX = -4095, 61439  # Elevation, 0.1 m (saturating at both ends)
ELEV_UNAVAILABLE = -4096
ACCURACY_MAX = 254  # Semi{Major,Minor}AxisAccuracy, 0.05 m; 254 = >= 12.7 m
ACCURACY_UNAVAILABLE = 255
ORIENTATION_MAX = 65534  # SemiMajorAxisOrientation, 360/65535 degree
ORIENTATION_UNAVAILABLE = 65535
SPEED_MAX = 8190  # Speed, 0.02 m/s; 8190 = >= 163.8 m/s
SPEED_UNAVAILABLE = 8191
HEADING_MAX = 28799  # Heading, 0.0125 degree clockwise from north
HEADING_UNAVAILABLE = 28800
ANGLE_MIN, ANGLE_MAX = -126, 126  # SteeringWheelAngle, 1.5 degree, clockwise positive
ANGLE_UNAVAILABLE = 127
ACCEL_MIN, ACCEL_MAX = -2000, 2000  # Acceleration, 0.01 m/s²
ACCEL_UNAVAILABLE = 2001
VERT_MIN, VERT_MAX = -126, 127  # VerticalAcceleration, 0.02 G
VERT_UNAVAILABLE = -127
YAW_RATE_MIN, YAW_RATE_MAX = -32767, 32767  # YawRate, 0.01 degree/s, clockwise positive
WIDTH_MAX = 1023  # VehicleWidth, cm
LENGTH_MAX = 4095  # VehicleLength, cm

SPEED_UNIT = 0.02  # m/s
HEADING_UNIT = 0.0125  # degree
LATLON_UNIT = 1e-7  # degree
ELEV_UNIT = 0.1  # m
ACCURACY_UNIT = 0.05  # m
ORIENTATION_UNIT = 360.0 / 65535.0  # degree
ANGLE_UNIT = 1.5  # degree
ACCEL_UNIT = 0.01  # m/s²
VERT_UNIT = 0.02  # G
YAW_RATE_UNIT = 0.01  # degree/s
SIZE_UNIT = 0.01  # m

TRANSMISSION_STATES = (
    "neutral",
    "park",
    "forwardGears",
    "reverseGears",
    "reserved1",
    "reserved2",
    "reserved3",
    "unavailable",
)
CONTROL_STATES = ("unavailable", "off", "on", "engaged")  # traction, abs, scs
BRAKE_BOOST_STATES = ("unavailable", "off", "on")
AUX_BRAKE_STATES = ("unavailable", "off", "on", "reserved")
#: BrakeAppliedStatus named bits, in wire order (bit 0 first = most significant of 5).
WHEEL_BRAKE_BITS = ("unavailable", "leftFront", "leftRear", "rightFront", "rightRear")
WHEEL_BRAKES_UNAVAILABLE = 0b10000

ASN_PATH = Path(__file__).with_name("j2735.asn")


class BsmDecodeError(ValueError):
    """The bytes are not a valid J2735 BSM MessageFrame (message says why)."""


class BsmCore(NamedTuple):
    """BSM Part I (``BSMcoreData``) in J2735 integer units, field by field.

    Names follow the ASN.1 (``long`` -> ``lon``, nested sequences flattened). Defaults are
    the standard's "unavailable" codes, so a sender fills only what it knows. Immutable;
    ``core._replace(speed=...)`` gives a modified copy. (A named tuple rather than a
    frozen dataclass: built for every message received, and four times cheaper to build.)

    Attributes:
        msg_cnt: MsgCount 0..127, +1 per message from one sender, wrapping.
        temp_id: TemporaryID, 4 bytes.
        sec_mark: DSecond, milliseconds within the UTC minute (65535 unavailable).
        lat, lon: 1e-7 degree (900000001 / 1800000001 unavailable).
        elev: 0.1 m above the WGS-84 ellipsoid (-4096 unavailable).
        semi_major, semi_minor: position error ellipse axes, 0.05 m (255 unavailable).
        orientation: ellipse orientation, 360/65535 degree from north (65535 unavailable).
        transmission: TransmissionState name.
        speed: 0.02 m/s (8191 unavailable).
        heading: 0.0125 degree, clockwise from north (28800 unavailable).
        angle: steering wheel angle, 1.5 degree, clockwise positive (127 unavailable).
        accel_long, accel_lat: 0.01 m/s² (2001 unavailable).
        accel_vert: 0.02 G (-127 unavailable).
        yaw_rate: 0.01 degree/s, clockwise positive.
        wheel_brakes: BrakeAppliedStatus as a 5-bit integer, bit 4 = named bit 0
            ("unavailable"), bit 0 = named bit 4 ("rightRear"); 0b10000 = unavailable.
        traction, abs, scs, brake_boost, aux_brakes: enumeration names.
        width, length: vehicle size, cm (0 when unknown).
    """

    msg_cnt: int
    temp_id: bytes
    sec_mark: int
    lat: int
    lon: int
    elev: int = ELEV_UNAVAILABLE
    semi_major: int = ACCURACY_UNAVAILABLE
    semi_minor: int = ACCURACY_UNAVAILABLE
    orientation: int = ORIENTATION_UNAVAILABLE
    transmission: str = "unavailable"
    speed: int = SPEED_UNAVAILABLE
    heading: int = HEADING_UNAVAILABLE
    angle: int = ANGLE_UNAVAILABLE
    accel_long: int = ACCEL_UNAVAILABLE
    accel_lat: int = ACCEL_UNAVAILABLE
    accel_vert: int = VERT_UNAVAILABLE
    yaw_rate: int = 0
    wheel_brakes: int = WHEEL_BRAKES_UNAVAILABLE
    traction: str = "unavailable"
    abs: str = "unavailable"
    scs: str = "unavailable"
    brake_boost: str = "unavailable"
    aux_brakes: str = "unavailable"
    width: int = 0
    length: int = 0


@dataclass(frozen=True, slots=True)
class Bsm:
    """A decoded BSM: the core plus what else the frame carried (kept opaque).

    Attributes:
        core: Part I.
        part_ii_ids: PartII-Id of each Part II element (0 vehicle safety, 1 special
            vehicle, 2 supplemental vehicle extensions), in frame order.
        regional_ids: RegionId of each regional extension, in frame order.
    """

    core: BsmCore
    part_ii_ids: tuple[int, ...] = field(default=())
    regional_ids: tuple[int, ...] = field(default=())


# Integer fields and their valid ASN.1 ranges, checked on both encode and decode.
# asn1tools does not check constraints on decode by default (and checking them there
# is slower), while UPER can carry out-of-range values in the spare bit patterns of a
# constrained integer's field (Latitude's 31 bits hold up to 2^31 - 1 offsets).
_INT_RANGES: dict[str, tuple[int, int]] = {
    "msg_cnt": (0, MSG_CNT_MAX),
    "sec_mark": (0, SEC_MARK_MAX),
    "lat": (LAT_MIN, LAT_UNAVAILABLE),
    "lon": (LON_MIN, LON_UNAVAILABLE),
    "elev": (ELEV_UNAVAILABLE, ELEV_MAX),
    "semi_major": (0, ACCURACY_UNAVAILABLE),
    "semi_minor": (0, ACCURACY_UNAVAILABLE),
    "orientation": (0, ORIENTATION_UNAVAILABLE),
    "speed": (0, SPEED_UNAVAILABLE),
    "heading": (0, HEADING_UNAVAILABLE),
    "angle": (ANGLE_MIN, ANGLE_UNAVAILABLE),
    "accel_long": (ACCEL_MIN, ACCEL_UNAVAILABLE),
    "accel_lat": (ACCEL_MIN, ACCEL_UNAVAILABLE),
    "accel_vert": (VERT_UNAVAILABLE, VERT_MAX),
    "yaw_rate": (YAW_RATE_MIN, YAW_RATE_MAX),
    "wheel_brakes": (0, 0b11111),
    "width": (0, WIDTH_MAX),
    "length": (0, LENGTH_MAX),
}
_ENUMS: dict[str, tuple[str, ...]] = {
    "transmission": TRANSMISSION_STATES,
    "traction": CONTROL_STATES,
    "abs": CONTROL_STATES,
    "scs": CONTROL_STATES,
    "brake_boost": BRAKE_BOOST_STATES,
    "aux_brakes": AUX_BRAKE_STATES,
}


_INT_NAMES = tuple(_INT_RANGES)
_INT_LO = tuple(lo for lo, _ in _INT_RANGES.values())
_INT_HI = tuple(hi for _, hi in _INT_RANGES.values())
_get_ints = operator.attrgetter(*_INT_NAMES)
_ENUM_NAMES = tuple(_ENUMS)
_ENUM_SETS = tuple(frozenset(v) for v in _ENUMS.values())
_get_enums = operator.attrgetter(*_ENUM_NAMES)


def _bit_field_holds_more(lo: int, hi: int) -> bool:
    """Whether UPER's bit field for INTEGER (lo..hi) can carry values above ``hi``."""
    span = hi - lo + 1
    return (1 << (span - 1).bit_length()) > span


_WIDE = {k: hi for k, (lo, hi) in _INT_RANGES.items() if _bit_field_holds_more(lo, hi)}
_WIDE_NAMES = tuple(_WIDE)
_WIDE_HI = tuple(_WIDE.values())
_get_wide = operator.attrgetter(*_WIDE_NAMES)


def check_core(core: BsmCore) -> None:
    """Raise ``ValueError`` naming the first field outside its J2735 range."""
    # One pass over tuples: this runs for every message sent and received.
    for name, v, lo, hi in zip(_INT_NAMES, _get_ints(core), _INT_LO, _INT_HI):
        if v.__class__ is not int or not lo <= v <= hi:
            raise ValueError(f"BSM field {name}={v!r} outside J2735 range [{lo}, {hi}]")
    for name, v, allowed in zip(_ENUM_NAMES, _get_enums(core), _ENUM_SETS):
        if v not in allowed:
            raise ValueError(f"BSM field {name}={v!r} not one of {sorted(allowed)}")
    if core.temp_id.__class__ is not bytes or len(core.temp_id) != 4:
        raise ValueError(f"BSM temp_id must be 4 bytes, got {core.temp_id!r}")


@functools.cache
def _spec() -> tuple[Any, Any]:
    """The compiled (MessageFrame, BasicSafetyMessage) UPER types, once per process."""
    try:
        import asn1tools  # imported here: only processes that speak J2735 pay for it
    except ModuleNotFoundError:
        raise DependencyMissing(
            "J2735 BSMs need asn1tools: pip install 'openconvoy[vehicle]'", name="asn1tools"
        ) from None

    spec = asn1tools.compile_files(str(ASN_PATH), "uper")
    return spec.types["MessageFrame"], spec.types["BasicSafetyMessage"]


def warm_up() -> None:
    """Compile the ASN.1 module now (done lazily otherwise, on the first message)."""
    _spec()


def _to_asn(core: BsmCore) -> dict[str, Any]:
    return {
        "coreData": {
            "msgCnt": core.msg_cnt,
            "id": core.temp_id,
            "secMark": core.sec_mark,
            "lat": core.lat,
            "long": core.lon,
            "elev": core.elev,
            "accuracy": {
                "semiMajor": core.semi_major,
                "semiMinor": core.semi_minor,
                "orientation": core.orientation,
            },
            "transmission": core.transmission,
            "speed": core.speed,
            "heading": core.heading,
            "angle": core.angle,
            "accelSet": {
                "long": core.accel_long,
                "lat": core.accel_lat,
                "vert": core.accel_vert,
                "yaw": core.yaw_rate,
            },
            "brakes": {
                # BIT STRING values are (bytes, bit count), bits from the most significant.
                "wheelBrakes": (bytes([core.wheel_brakes << 3]), 5),
                "traction": core.traction,
                "abs": core.abs,
                "scs": core.scs,
                "brakeBoost": core.brake_boost,
                "auxBrakes": core.aux_brakes,
            },
            "size": {"width": core.width, "length": core.length},
        }
    }


_new_core = tuple.__new__


def _from_asn(c: dict[str, Any]) -> BsmCore:
    acc, accel, brakes, size = c["accuracy"], c["accelSet"], c["brakes"], c["size"]
    wb_bytes, wb_len = brakes["wheelBrakes"]
    if wb_len != 5 or len(wb_bytes) != 1:
        raise BsmDecodeError(f"wheelBrakes has {wb_len} bits, expected 5")
    # Positional, through tuple.__new__: the named tuple's keyword constructor costs more
    # than the rest of this function (order: BsmCore's fields).
    return _new_core(
        BsmCore,
        (
            c["msgCnt"],
            bytes(c["id"]),
            c["secMark"],
            c["lat"],
            c["long"],
            c["elev"],
            acc["semiMajor"],
            acc["semiMinor"],
            acc["orientation"],
            c["transmission"],
            c["speed"],
            c["heading"],
            c["angle"],
            accel["long"],
            accel["lat"],
            accel["vert"],
            accel["yaw"],
            wb_bytes[0] >> 3,
            brakes["traction"],
            brakes["abs"],
            brakes["scs"],
            brakes["brakeBoost"],
            brakes["auxBrakes"],
            size["width"],
            size["length"],
        ),
    )


# The MessageFrame around a BSM is its first two octets (extension bit 0, messageId 20 in
# 15 bits) and the value as an open type: an X.691 length determinant (one octet below
# 128, two below 16384; larger ones fragment and are never a BSM) and the BSM's octets.
# Written and read here directly, since asn1tools would spend as long on this wrapper as
# on the BSM itself (tests/comms/test_bsm.py holds it equal to asn1tools' encoding).


def _frame_header(n: int) -> bytes:
    if n < 0x80:
        return BSM_FRAME_PREFIX + bytes((n,))
    return BSM_FRAME_PREFIX + bytes((0x80 | (n >> 8), n & 0xFF))


def _frame_value(data: bytes) -> bytes:
    b = data[2]
    if b < 0x80:
        start, n = 3, b
    elif b < 0xC0 and len(data) >= 4:
        start, n = 4, ((b & 0x3F) << 8) | data[3]
    else:
        raise BsmDecodeError("MessageFrame value length is fragmented or truncated")
    if len(data) < start + n:
        raise BsmDecodeError(f"truncated MessageFrame: {len(data)} octets, value needs {start + n}")
    return data[start : start + n]


# A core-only BSM (no Part II, no regional, no extension: its 3 preamble bits are 0) is 37
# octets: the preamble, the fixed 290-bit core, 3 bits of padding. Its fields are read
# here with shifts; asn1tools reads every other BSM. (name, bits, lower bound or the
# enumeration's names), in wire order; tests/comms/test_bsm.py holds both readings equal.
_CORE_FIELDS: tuple[tuple[str, int, Any], ...] = (
    ("msg_cnt", 7, 0),
    ("temp_id", 32, None),
    ("sec_mark", 16, 0),
    ("lat", 31, LAT_MIN),
    ("lon", 32, LON_MIN),
    ("elev", 16, ELEV_UNAVAILABLE),
    ("semi_major", 8, 0),
    ("semi_minor", 8, 0),
    ("orientation", 16, 0),
    ("transmission", 3, TRANSMISSION_STATES),
    ("speed", 13, 0),
    ("heading", 15, 0),
    ("angle", 8, ANGLE_MIN),
    ("accel_long", 12, ACCEL_MIN),
    ("accel_lat", 12, ACCEL_MIN),
    ("accel_vert", 8, VERT_UNAVAILABLE),
    ("yaw_rate", 16, YAW_RATE_MIN),
    ("wheel_brakes", 5, 0),
    ("traction", 2, CONTROL_STATES),
    ("abs", 2, CONTROL_STATES),
    ("scs", 2, CONTROL_STATES),
    ("brake_boost", 2, BRAKE_BOOST_STATES),
    ("aux_brakes", 2, AUX_BRAKE_STATES),
    ("width", 10, 0),
    ("length", 12, 0),
)
CORE_ONLY_OCTETS = 37


def _core_layout() -> tuple[tuple[int, int, Any], ...]:
    out, pos = [], 3  # after the preamble
    for _, bits, lo in _CORE_FIELDS:
        pos += bits
        out.append((CORE_ONLY_OCTETS * 8 - pos, (1 << bits) - 1, lo))
    assert pos == 3 + 290
    return tuple(out)


_LAYOUT = _core_layout()


def _decode_core_only(value: bytes) -> BsmCore:
    """The core of a core-only BSM value (37 octets, preamble 000), read directly."""
    v = int.from_bytes(value, "big")
    fields: list[Any] = []
    append = fields.append
    for shift, mask, lo in _LAYOUT:
        x = (v >> shift) & mask
        if lo.__class__ is int:
            append(x + lo)
        elif lo is None:
            append(x.to_bytes(4, "big"))
        elif x < len(lo):
            append(lo[x])
        else:
            raise BsmDecodeError(f"enumeration index {x} out of range")
    return _new_core(BsmCore, fields)


def encode_frame(core: BsmCore, *, check: bool = True) -> bytes:
    """UPER-encode ``core`` as a J2735 MessageFrame carrying a core-only BSM.

    With ``check`` (default) every field is range-checked first (``ValueError`` if not);
    callers that built the core with the clamping mapping may skip it.
    """
    if check:
        check_core(core)
    value = _spec()[1].encode(_to_asn(core))
    return _frame_header(len(value)) + value


def decode_frame(data: bytes) -> Bsm:
    """Decode one UPER MessageFrame; raise ``BsmDecodeError`` unless it is a valid BSM.

    Trailing octets after the frame are ignored (some stacks pad datagrams); Part II and
    regional contents are skipped, only their ids are reported.
    """
    if len(data) < 3 or data[:2] != BSM_FRAME_PREFIX:
        # Cheap early exit for most foreign traffic; another messageId is named below.
        if len(data) >= 2 and data[0] & 0x80 == 0:
            msg_id = ((data[0] << 8) | data[1]) & 0x7FFF
            if msg_id != BSM_MESSAGE_ID:
                raise BsmDecodeError(f"not a BSM: MessageFrame messageId {msg_id}")
        raise BsmDecodeError("not a J2735 BSM MessageFrame (too short or bad header)")
    value = _frame_value(data)
    try:
        if len(value) == CORE_ONLY_OCTETS and value[0] < 0x20:  # preamble 000
            core, part_ii, regional = _decode_core_only(value), (), ()
        else:
            bsm = _spec()[1].decode(value)
            core = _from_asn(bsm["coreData"])
            part_ii = tuple(p["partII-Id"] for p in bsm.get("partII", ()))
            regional = tuple(r["regionId"] for r in bsm.get("regional", ()))
    except BsmDecodeError:
        raise
    except Exception as exc:  # asn1tools raises many types on garbage; all mean "invalid"
        raise BsmDecodeError(f"invalid UPER: {type(exc).__name__}: {exc}") from None
    # Only fields whose UPER bit field can hold values past the type's range need a
    # check here: the others cannot be out of range once decoded (and asn1tools rejects
    # enumeration indexes it does not know).
    for name, v, hi in zip(_WIDE_NAMES, _get_wide(core), _WIDE_HI):
        if v > hi:
            raise BsmDecodeError(f"BSM field {name}={v!r} outside J2735 range (max {hi})")
    return Bsm(core, part_ii, regional)


def _avail(v: int, unavailable: int, unit: float) -> float | None:
    return None if v == unavailable else v * unit


def to_physical(core: BsmCore) -> dict[str, Any]:
    """Core fields in physical units (None where the sender said "unavailable").

    Keys: msg_cnt, temp_id (hex), sec_mark_s, lat_deg, lon_deg, elev_m, semi_major_m,
    semi_minor_m, orientation_deg, transmission, speed_mps, heading_deg (compass,
    clockwise from north), steering_angle_deg, accel_long_mps2, accel_lat_mps2,
    accel_vert_g, yaw_rate_dps (clockwise positive), wheel_brakes (names of set bits),
    traction, abs, scs, brake_boost, aux_brakes, width_m, length_m.
    """
    return {
        "msg_cnt": core.msg_cnt,
        "temp_id": core.temp_id.hex().upper(),
        "sec_mark_s": None if core.sec_mark == SEC_MARK_UNAVAILABLE else core.sec_mark / 1000,
        "lat_deg": _avail(core.lat, LAT_UNAVAILABLE, LATLON_UNIT),
        "lon_deg": _avail(core.lon, LON_UNAVAILABLE, LATLON_UNIT),
        "elev_m": _avail(core.elev, ELEV_UNAVAILABLE, ELEV_UNIT),
        "semi_major_m": _avail(core.semi_major, ACCURACY_UNAVAILABLE, ACCURACY_UNIT),
        "semi_minor_m": _avail(core.semi_minor, ACCURACY_UNAVAILABLE, ACCURACY_UNIT),
        "orientation_deg": _avail(core.orientation, ORIENTATION_UNAVAILABLE, ORIENTATION_UNIT),
        "transmission": core.transmission,
        "speed_mps": _avail(core.speed, SPEED_UNAVAILABLE, SPEED_UNIT),
        "heading_deg": _avail(core.heading, HEADING_UNAVAILABLE, HEADING_UNIT),
        "steering_angle_deg": _avail(core.angle, ANGLE_UNAVAILABLE, ANGLE_UNIT),
        "accel_long_mps2": _avail(core.accel_long, ACCEL_UNAVAILABLE, ACCEL_UNIT),
        "accel_lat_mps2": _avail(core.accel_lat, ACCEL_UNAVAILABLE, ACCEL_UNIT),
        "accel_vert_g": _avail(core.accel_vert, VERT_UNAVAILABLE, VERT_UNIT),
        "yaw_rate_dps": core.yaw_rate * YAW_RATE_UNIT,
        "wheel_brakes": [
            name for i, name in enumerate(WHEEL_BRAKE_BITS) if core.wheel_brakes & (0b10000 >> i)
        ],
        "traction": core.traction,
        "abs": core.abs,
        "scs": core.scs,
        "brake_boost": core.brake_boost,
        "aux_brakes": core.aux_brakes,
        "width_m": core.width * SIZE_UNIT,
        "length_m": core.length * SIZE_UNIT,
    }


def core_as_dict(core: BsmCore) -> dict[str, Any]:
    """The core's raw J2735 integers as a plain dict (temp_id as upper-case hex)."""
    d = core._asdict()
    d["temp_id"] = core.temp_id.hex().upper()
    return d


def peek_temp_id(data: bytes) -> int | None:
    """The TemporaryID of a BSM MessageFrame read straight from its bits, without decoding,
    as a 32-bit integer (``int.from_bytes(temp_id, "big")``).

    UPER lays a BSM out as: the frame's extension bit and 15-bit messageId (``00 14``),
    the open type's length determinant (one octet below 128, two from 128 on), then the
    BSM's extension bit, its two OPTIONAL bits, the 7-bit msgCnt and the 32-bit id. A
    receiver uses this to drop foreign traffic for well under a microsecond a datagram
    instead of a full decode (~50 us). None when ``data`` is not a BSM frame or too short;
    a frame whose id is known must still be decoded in full.
    """
    if data[:2] != BSM_FRAME_PREFIX or len(data) < 9:
        return None
    if data[2] < 0x80:
        bits = int.from_bytes(data[3:9], "big")  # 48 bits: 3 + 7 + 32 + 6
    elif data[2] < 0xC0 and len(data) >= 10:
        bits = int.from_bytes(data[4:10], "big")
    else:
        return None
    return (bits >> 6) & 0xFFFFFFFF
