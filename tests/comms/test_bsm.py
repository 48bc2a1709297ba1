"""The J2735 BSM codec: interop vectors, ranges, round trips, rejection of bad frames."""

from __future__ import annotations

import pytest
from comms_testdata import load_vectors
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms import bsm as j
from openconvoy.comms.bsm import Bsm, BsmCore, BsmDecodeError, decode_frame, encode_frame

VECTORS = load_vectors()


def _expected_core(fields: dict) -> BsmCore:
    """The vector's recorded core values as a BsmCore."""
    acc, accel, brakes, size = (
        fields["accuracy"],
        fields["accelSet"],
        fields["brakes"],
        fields["size"],
    )
    return BsmCore(
        msg_cnt=fields["msgCnt"],
        temp_id=bytes.fromhex(fields["id"]),
        sec_mark=fields["secMark"],
        lat=fields["lat"],
        lon=fields["long"],
        elev=fields["elev"],
        semi_major=acc["semiMajor"],
        semi_minor=acc["semiMinor"],
        orientation=acc["orientation"],
        transmission=fields["transmission"],
        speed=fields["speed"],
        heading=fields["heading"],
        angle=fields["angle"],
        accel_long=accel["long"],
        accel_lat=accel["lat"],
        accel_vert=accel["vert"],
        yaw_rate=accel["yaw"],
        wheel_brakes=int(brakes["wheelBrakes"], 2),
        traction=brakes["traction"],
        abs=brakes["abs"],
        scs=brakes["scs"],
        brake_boost=brakes["brakeBoost"],
        aux_brakes=brakes["auxBrakes"],
        width=size["width"],
        length=size["length"],
    )


def test_there_are_54_vectors_covering_all_kinds():
    assert len(VECTORS) == 54
    part_ii = {p["partII-Id"] for v in VECTORS for p in v["partII"]}
    assert part_ii == {0, 1, 2}
    assert any(v["regional"] for v in VECTORS)
    assert any(not v["partII"] and not v["regional"] for v in VECTORS)


@pytest.mark.parametrize("i", range(len(VECTORS)))
def test_interop_vector_decodes_to_recorded_core(i):
    v = VECTORS[i]
    data = bytes.fromhex(v["hex"])
    assert len(data) == v["length_bytes"]
    got = decode_frame(data)
    assert got.core == _expected_core(v["decoded_core_fields"])
    assert got.part_ii_ids == tuple(p["partII-Id"] for p in v["partII"])
    assert got.regional_ids == tuple(r["regionId"] for r in v["regional"])
    phys = j.to_physical(got.core)
    units = v["physical_units"]
    # The vectors' physical values (lat/long 1e-7 degree, elev 0.1 m, speed 0.02 m/s, ...)
    for ours, theirs in [
        ("lat_deg", "lat_deg"),
        ("lon_deg", "long_deg"),
        ("elev_m", "elev_m"),
        ("speed_mps", "speed_mps"),
        ("heading_deg", "heading_deg"),
        ("steering_angle_deg", "angle_deg"),
        ("accel_long_mps2", "accel_long_mps2"),
        ("accel_lat_mps2", "accel_lat_mps2"),
        ("accel_vert_g", "accel_vert_g"),
        ("yaw_rate_dps", "yaw_rate_dps"),
        ("sec_mark_s", "secMark_s"),
        ("width_m", "width_m"),
        ("length_m", "length_m"),
    ]:
        if units.get(theirs) is None:
            assert phys[ours] is None, ours
        else:
            assert phys[ours] == pytest.approx(units[theirs], abs=1e-9), ours


@pytest.mark.parametrize("i", [1, 5, 8, 16, 43, 52])  # the core-only frames
def test_core_only_vectors_reencode_bit_exactly(i):
    data = bytes.fromhex(VECTORS[i]["hex"])
    assert not VECTORS[i]["partII"] and not VECTORS[i]["regional"]
    assert encode_frame(decode_frame(data).core) == data


def test_core_only_frame_is_40_bytes_and_starts_00_14():
    core = BsmCore(msg_cnt=5, temp_id=b"\x01\x02\x03\x04", sec_mark=1234, lat=1, lon=2)
    data = encode_frame(core)
    assert data[:2] == b"\x00\x14"
    # 2 octets header + 1 length octet + ceil((3 + 290) / 8) = 37 octets of BSM
    assert len(data) == 40 and data[2] == 37
    assert decode_frame(data) == Bsm(core)


def test_trailing_padding_is_ignored():
    data = bytes.fromhex(VECTORS[1]["hex"])
    assert decode_frame(data + b"\x00\x00").core == decode_frame(data).core


@pytest.mark.parametrize(
    "field,value",
    [
        ("lat", j.LAT_UNAVAILABLE + 1),
        ("lon", j.LON_MIN - 1),
        ("speed", 8192),
        ("heading", 28801),
        ("msg_cnt", 128),
        ("elev", -4097),
        ("accel_vert", -128),
        ("temp_id", b"\x01\x02\x03"),
        ("transmission", "overdrive"),
        ("brake_boost", "engaged"),  # engaged is valid for traction, not brake boost
        ("speed", 1.5),
    ],
)
def test_encode_rejects_out_of_range(field, value):
    core = BsmCore(msg_cnt=0, temp_id=b"abcd", sec_mark=0, lat=0, lon=0)._replace(**{field: value})
    with pytest.raises(ValueError, match=field):
        encode_frame(core)


def test_decode_rejects_other_messages_and_garbage():
    with pytest.raises(BsmDecodeError, match="messageId 19"):
        decode_frame(bytes.fromhex("0013") + bytes(30))  # a SPaT frame header
    with pytest.raises(BsmDecodeError):
        decode_frame(b"")
    with pytest.raises(BsmDecodeError):
        decode_frame(bytes.fromhex(VECTORS[1]["hex"])[:20])  # truncated
    # lat field (after the 3 preamble bits, msgCnt, id, secMark) set to all ones:
    # a value above 900000001 that fits the 31-bit field
    core = BsmCore(msg_cnt=0, temp_id=b"abcd", sec_mark=0, lat=0, lon=0)
    bits = int.from_bytes(encode_frame(core)[3:], "big")
    n = 37 * 8
    lat_start = 3 + 7 + 32 + 16
    bits |= ((1 << 31) - 1) << (n - lat_start - 31)
    data = encode_frame(core)[:3] + bits.to_bytes(37, "big")
    with pytest.raises(BsmDecodeError, match="lat"):
        decode_frame(data)


def _cores():
    def ints(lo, hi):
        return st.integers(lo, hi)

    return st.builds(
        BsmCore,
        msg_cnt=ints(0, 127),
        temp_id=st.binary(min_size=4, max_size=4),
        sec_mark=ints(0, 65535),
        lat=ints(j.LAT_MIN, j.LAT_UNAVAILABLE),
        lon=ints(j.LON_MIN, j.LON_UNAVAILABLE),
        elev=ints(j.ELEV_UNAVAILABLE, j.ELEV_MAX),
        semi_major=ints(0, 255),
        semi_minor=ints(0, 255),
        orientation=ints(0, 65535),
        transmission=st.sampled_from(j.TRANSMISSION_STATES),
        speed=ints(0, 8191),
        heading=ints(0, 28800),
        angle=ints(-126, 127),
        accel_long=ints(-2000, 2001),
        accel_lat=ints(-2000, 2001),
        accel_vert=ints(-127, 127),
        yaw_rate=ints(-32767, 32767),
        wheel_brakes=ints(0, 31),
        traction=st.sampled_from(j.CONTROL_STATES),
        abs=st.sampled_from(j.CONTROL_STATES),
        scs=st.sampled_from(j.CONTROL_STATES),
        brake_boost=st.sampled_from(j.BRAKE_BOOST_STATES),
        aux_brakes=st.sampled_from(j.AUX_BRAKE_STATES),
        width=ints(0, 1023),
        length=ints(0, 4095),
    )


@settings(max_examples=300, deadline=None)
@given(_cores())
def test_any_core_round_trips_exactly(core):
    data = encode_frame(core)
    assert len(data) == 40  # the core is a fixed 290 bits
    assert decode_frame(data).core == core


def test_physical_units_and_unavailable():
    core = BsmCore(
        msg_cnt=1,
        temp_id=b"\x00\x00\x00\x2a",
        sec_mark=59999,
        lat=473977000,
        lon=85456000,
        speed=100,
        heading=7200,
        wheel_brakes=0b01001,
    )
    p = j.to_physical(core)
    assert p["lat_deg"] == pytest.approx(47.3977)
    assert p["lon_deg"] == pytest.approx(8.5456)
    assert p["speed_mps"] == pytest.approx(2.0)
    assert p["heading_deg"] == pytest.approx(90.0)
    assert p["sec_mark_s"] == pytest.approx(59.999)
    assert p["elev_m"] is None and p["accel_long_mps2"] is None
    assert p["steering_angle_deg"] is None
    assert p["wheel_brakes"] == ["leftFront", "rightRear"]
    assert p["temp_id"] == "0000002A"


@settings(max_examples=200, deadline=None)
@given(_cores())
def test_encode_frame_is_bytes_equal_to_asn1tools_message_frame(core):
    # Our own MessageFrame wrapper against asn1tools' encoding of the whole frame; and
    # any out-of-range bit pattern the decoder lets through would fail check_core.
    data = encode_frame(core)
    assert type(data) is bytes and hash(data) is not None
    frame_t, bsm_t = j._spec()
    assert data == bytes(frame_t.encode({"messageId": 20, "value": bsm_t.encode(j._to_asn(core))}))
    j.check_core(decode_frame(data).core)


def test_two_octet_value_lengths_and_truncation():
    big = max((bytes.fromhex(v["hex"]) for v in VECTORS), key=len)
    assert big[2] & 0xC0 == 0x80  # a 2-octet length determinant (value >= 128 octets)
    frame_t, bsm_t = j._spec()
    assert decode_frame(big).core == j._from_asn(
        bsm_t.decode(frame_t.decode(big)["value"])["coreData"]
    )
    for cut in (3, 4, 100, len(big) - 1):
        with pytest.raises(BsmDecodeError):
            decode_frame(big[:cut])
    with pytest.raises(BsmDecodeError, match="fragmented"):
        decode_frame(b"\x00\x14\xc1" + bytes(40))


@settings(max_examples=300, deadline=None)
@given(_cores())
def test_core_only_frames_read_directly_equal_asn1tools(core):
    data = encode_frame(core)
    frame_t, bsm_t = j._spec()
    via_asn1tools = j._from_asn(bsm_t.decode(frame_t.decode(data)["value"])["coreData"])
    assert len(data) == 40 and j._decode_core_only(data[3:]) == via_asn1tools == core


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=37, max_size=37))
def test_any_core_only_bit_pattern_reads_the_same_both_ways(value):
    value = bytes([value[0] & 0x1F]) + value[1:]  # preamble 000: core only
    data = b"\x00\x14\x25" + value
    try:
        ours = decode_frame(data).core
    except BsmDecodeError:
        ours = None
    frame_t, bsm_t = j._spec()
    try:
        theirs = j._from_asn(bsm_t.decode(value)["coreData"])
        j.check_core(theirs)
    except Exception:
        theirs = None
    assert ours == theirs
