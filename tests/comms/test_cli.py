"""``openconvoy bsm decode`` in-process, argument handling, and the tools' pure parts.
(``bsm listen`` / ``bsm send`` over sockets: test_netns.py.)"""

from __future__ import annotations

import json

import pytest
from comms_testdata import load_vectors

from openconvoy import cli
from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as compat
from openconvoy.comms import multicast, tools
from openconvoy.comms.geodesy import Origin
from openconvoy.core.state import VehicleState

VECTORS = load_vectors()


def _run(capsys, *argv):
    rc = cli.main(list(argv))
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_decode_prints_core_fields_in_physical_units(capsys):
    v = VECTORS[3]  # jpo-ode frame with all three Part II types
    rc, out, err = _run(capsys, "bsm", "decode", v["hex"])
    assert rc == 0 and err == ""
    fields = dict(line.split(None, 1) for line in out.strip().splitlines())
    assert fields["temp_id"] == "54310000"
    assert fields["msg_cnt"] == "46"
    assert float(fields["lat_deg"]) == pytest.approx(38.956121, abs=1e-9)
    assert float(fields["lon_deg"]) == pytest.approx(-77.1500090, abs=1e-9)
    assert float(fields["speed_mps"]) == pytest.approx(0.06)
    assert float(fields["heading_deg"]) == pytest.approx(228.3)
    assert float(fields["elev_m"]) == pytest.approx(68.7)
    assert fields["steering_angle_deg"] == "unavailable"
    assert fields["part_ii_ids"] == "[0, 1, 2]"


def test_decode_json_and_loose_hex(capsys):
    h = VECTORS[1]["hex"]
    spaced = "0x" + " ".join(h[i : i + 2] for i in range(0, len(h), 2))
    rc, out, _ = _run(capsys, "bsm", "decode", "--json", *spaced.split(" ", 3))
    assert rc == 0
    d = json.loads(out)
    assert d["temp_id"] == "010C0C0A" and d["speed_mps"] == pytest.approx(2.0)
    assert d["lat_deg"] == pytest.approx(3.8954961) and d["regional_ids"] == []


@pytest.mark.parametrize(
    "arg,message",
    [
        ("0013" + "00" * 38, "not a valid J2735 BSM frame: not a BSM: MessageFrame messageId 19"),
        ("00142500", "not a valid J2735 BSM frame"),
        ("xyz", "not hexadecimal"),
    ],
)
def test_decode_errors_are_one_line(capsys, arg, message):
    rc, out, err = _run(capsys, "bsm", "decode", arg)
    assert rc == 2 and out == ""
    assert err.startswith("openconvoy: error: " + message) and err.count("\n") == 1


def test_send_and_listen_reject_unknown_interface(capsys):
    rc, _, err = _run(capsys, "bsm", "send", "--iface", "no-such-if0")
    assert rc == 2 and "no network interface named 'no-such-if0'" in err
    rc, _, err = _run(capsys, "bsm", "listen", "--iface", "no-such-if0", "--timeout", "1")
    assert rc == 2 and "no network interface named 'no-such-if0'" in err


def test_bsm_requires_a_subcommand(capsys):
    assert cli.main(["bsm"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("openconvoy: error:") and "SUBCOMMAND" in line


def test_cli_defaults_match_the_transport():
    parser = cli.build_parser()
    args = parser.parse_args(["bsm", "listen", "--iface", "x"])
    assert args.group == multicast.DEFAULT_GROUP and args.port == multicast.DEFAULT_PORT


def test_listen_lines():
    origin = Origin(28.6024, -81.2001, 0.0)
    core = j.BsmCore(
        msg_cnt=7, temp_id=bytes.fromhex("0a0b0c0d"), sec_mark=30_250, lat=286024000,
        lon=-812001000, speed=50, heading=7200,
    )  # fmt: skip
    t_rx = 1_700_000_010.300  # 30.3 s into its minute
    line = tools.describe_datagram(j.encode_frame(core), t_rx)
    assert line == (
        "id=0A0B0C0D cnt=  7 lat=28.6024000 lon=-81.2001000 speed=1.00 m/s "
        "heading=90.0000 deg age=0.050 s"
    )
    state = VehicleState(2, 100.0, 0.0, 0.0, 1.5, 0.0)
    line = tools.describe_datagram(compat.encode_state(state, origin, abort=True), 100.25)
    assert line.startswith("car=2 (compat) lat=28.6024000 lon=-81.2001000 speed=1.50 m/s")
    assert line.endswith("heading=90.0000 deg age=0.250 s ABORT")
    assert tools.describe_datagram(b"junk", 0.0) is None
    assert tools.describe_datagram(bytes.fromhex(VECTORS[0]["hex"]), 0.0).endswith(
        "partII=[1] regional=[128]"
    )


def test_multicast_sockets_validate_arguments():
    with pytest.raises(ValueError, match="not an IPv6 multicast group"):
        multicast.Ipv6Multicast("lo", group="fe80::1")
    with pytest.raises(ValueError, match="not an IPv4 multicast group"):
        multicast.Ipv4Multicast("lo", group="10.0.0.1")
    with pytest.raises(ValueError, match="hop limit"):
        multicast.Ipv6Multicast("lo", hop_limit=300)
    with pytest.raises(ValueError, match="no network interface"):
        multicast.Ipv6Multicast("no-such-if0")
    assert multicast.multicast_scope(multicast.ipaddress.IPv6Address("ff15::4f43")) == 5


def test_memory_bus_loops_back_and_detaches():
    bus = multicast.MemoryBus()
    a, b = bus.endpoint("a"), bus.endpoint("b")
    a.send(b"1")
    assert [d.data for d in a.recv_all()] == [b"1"] and b.recv_all()[0].source == "a"
    b.close()
    a.send(b"2")
    assert b.recv_all() == [] and len(a.recv_all()) == 1


def test_missing_asn1tools_is_a_one_line_error(capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "asn1tools", None)  # import fails
    j._spec.cache_clear()
    try:
        rc, _, err = _run(capsys, "bsm", "decode", VECTORS[1]["hex"])
    finally:
        j._spec.cache_clear()
    assert rc == 2
    assert (
        err == "openconvoy: error: J2735 BSMs need asn1tools: pip install 'openconvoy[vehicle]'\n"
    )
