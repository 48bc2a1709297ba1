"""``bsm listen | send --transport ros2``: the field tools on a convoy's ROS 2 V2V topic
(``comms.dds``, Cyclone DDS on the namespace's veth), unsigned and signed, the flags of the
other transport refused, ``--convoy``'s ``[v2v]`` as the defaults (of multicast too), and
``DdsTransport.wait`` blocking rather than spinning.

(That an rclpy node reads the topic's samples is test_dds.py's; here both ends are ours.)"""

from __future__ import annotations

import json
import sys
import time

import pytest

from openconvoy import cli
from openconvoy.comms import cli as comms_cli
from openconvoy.comms import dds
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.comms.netns import run_in_netns
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.tools import DEFAULT_SEND_ID
from openconvoy.convoy import V2VConfig

BSM = [sys.executable, "-m", "openconvoy.cli", "bsm"]
START = Origin(28.6, -81.2, 0.0)


def after(delay_s: float, argv: list[str]) -> list[str]:
    """``argv`` started ``delay_s`` (s) late: the listeners must be up first (interpreter
    start-up varies under load; the sender also waits for DDS discovery to match them)."""
    return ["sh", "-c", f'sleep {delay_s}; exec "$@"', "sh", *argv]


def _fields(line: str) -> dict[str, str]:
    """``key=value`` words of a ``bsm listen`` line (``cnt=  3`` included)."""
    words = line.replace("cnt= ", "cnt=").replace("cnt= ", "cnt=").split()
    return dict(w.split("=", 1) for w in words if "=" in w)


def _enu(line: str) -> tuple[float, float]:
    """East, north (m) from ``START`` of the position a listen line prints."""
    f = _fields(line)
    x, y, _ = geodetic_to_enu(START, float(f["lat"]), float(f["lon"]), 0.0)
    return float(x), float(y)


def test_the_cli_defaults_are_the_convoy_files_and_the_transports():
    assert comms_cli.DEFAULT_ROS2_TOPIC == dds.DEFAULT_TOPIC == V2VConfig().ros2_topic
    assert comms_cli.DEFAULT_ROS2_DOMAIN == dds.DEFAULT_DOMAIN == V2VConfig().ros2_domain
    assert comms_cli.TRANSPORTS == ("multicast", "ros2")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["listen", "--transport", "ros2", "--compat"], "--compat: multicast only, not with "
         "--transport ros2"),
        (["listen", "--transport", "ros2", "--group", "ff15::1"], "--group: multicast only"),
        (["listen", "--transport", "ros2", "--port", "4300"], "--port: multicast only"),
        # the default's value given explicitly is still a multicast flag
        (["send", "--transport", "ros2", "--group", "ff15::4f43"], "--group: multicast only"),
        (["send", "--transport", "ros2", "--hop-limit", "2"], "--hop-limit: multicast only"),
        (["send", "--transport", "ros2", "--compat-car", "1"], "--compat-car: multicast only"),
        (["listen", "--ros2-topic", "/lab/v2v"], "--ros2-topic: only with --transport ros2"),
        (["send", "--transport", "multicast", "--ros2-domain", "3"],
         "--ros2-domain: only with --transport ros2"),
        (["listen", "--transport", "ros2", "--ros2-domain", "233"], "--ros2-domain: 233 is out of range"),
        (["send", "--transport", "udp"], "--transport: invalid choice: 'udp'"),
        (["listen", "--transport", "ros2", "--ros2-topic", "lab/v2v"],
         "'lab/v2v' is not an absolute ROS 2 topic name"),
    ],
)  # fmt: skip
def test_a_flag_of_the_other_transport_is_one_line_and_exit_2(capsys, argv, message):
    rc = cli.main(["bsm", *argv, "--iface", "oc0"])
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert line.startswith("openconvoy") and message in line, line


@pytest.mark.parametrize("command", ["listen", "send"])
def test_an_unknown_interface_is_the_same_line_over_ros2(capsys, command):
    rc = cli.main(["bsm", command, "--iface", "no-such-if0", "--transport", "ros2"])
    assert rc == 2
    assert (
        capsys.readouterr().err == "openconvoy: error: no network interface named 'no-such-if0'\n"
    )


def test_a_ros2_convoy_file_gives_the_transport_and_its_topic(tmp_path, capsys):
    convoy = tmp_path / "lab.toml"
    convoy.write_text('[convoy]\nname = "lab"\n[v2v]\ntransport = "ros2"\nros2_topic = "v2v"\n')
    rc = cli.main(["bsm", "send", "--iface", "oc0", "--convoy", str(convoy), "--port", "4201"])
    assert rc == 2
    assert capsys.readouterr().err.strip() == (
        'openconvoy: error: --port: multicast only, not with the --convoy file\'s transport = "ros2"'
    )
    # the file's topic is the one opened (and this one is refused before any network use)
    rc = cli.main(["bsm", "send", "--iface", "oc0", "--convoy", str(convoy)])
    assert rc == 2
    assert "'v2v' is not an absolute ROS 2 topic name" in capsys.readouterr().err
    # --transport multicast overrides the file; its ROS 2 flags are then refused
    rc = cli.main(["bsm", "send", "--iface", "oc0", "--convoy", str(convoy), "--transport",
                   "multicast", "--ros2-domain", "1"])  # fmt: skip
    assert rc == 2
    assert "--ros2-domain: only with --transport ros2" in capsys.readouterr().err


@pytest.mark.netns
def test_send_and_listen_over_a_ros2_topic_and_nowhere_else():
    topic = ["--transport", "ros2", "--ros2-topic", "/lab/v2v", "--ros2-domain", "7"]
    send = [*BSM, "send", "--iface", "oc0", *topic, "--count", "5", "--rate", "10",
            "--lat", "28.6", "--lon", "-81.2", "--speed", "2", "--heading", "90",
            "--id", "0a0b0c0d"]  # fmt: skip
    listen = [*BSM, "listen", "--iface", "oc0"]
    heard, multicast, other_topic, sender = run_in_netns(
        [
            [*listen, *topic, "--count", "5", "--timeout", "25"],
            # the multicast group and the default topic: nothing goes there (listening
            # until well after the sender is done)
            [*listen, "--timeout", "10"],
            [*listen, "--transport", "ros2", "--ros2-domain", "7", "--timeout", "10"],
            after(2.0, send),
        ],
        timeout=40,
    )
    assert sender.returncode == 0, sender.stderr
    assert "sent 5 BSMs on oc0 to ROS 2 topic /lab/v2v (DDS domain 7)" in sender.stderr
    for p in (heard, multicast, other_topic):
        assert p.returncode == 0, p.stderr
    assert multicast.stdout == "" and other_topic.stdout == ""
    lines = heard.stdout.strip().splitlines()
    assert len(lines) == 5, lines
    for k, line in enumerate(lines):
        f = _fields(line)
        assert (f["id"], f["cnt"], f["speed"], f["heading"]) == (
            "0A0B0C0D",
            str(k),
            "2.00",
            "90.0000",
        )
        assert 0.0 <= float(f["age"]) < 1.0
        east, north = _enu(line)
        # 2 m/s east, one BSM each 0.1 s: at least 0.2 m a message (sleeps only run late)
        assert abs(north) < 0.02 and 0.2 * k - 0.02 <= east <= 0.2 * k + 1.0, (k, east, north)
    assert float(_fields(lines[0])["lat"]) == 28.6 and float(_fields(lines[0])["lon"]) == -81.2


@pytest.mark.netns
def test_signed_bsms_over_ros2_are_verified_as_over_multicast(tmp_path):
    convoy = tmp_path / "lab.toml"
    convoy.write_text(
        '[convoy]\nname = "lab"\n[v2v]\ntransport = "ros2"\nros2_topic = "/lab/v2v"\n'
        "ros2_domain = 5\n"
    )
    keys = tmp_path / "lab.keys"
    now = time.time()
    ks.init_authority(keys, "lab", now)
    ks.issue_vehicle(keys, "lab", 1, now)
    send = [*BSM, "send", "--iface", "oc0", "--count", "5", "--rate", "10", "--lat", "28.6",
            "--lon", "-81.2", "--speed", "3", "--heading", "0"]  # fmt: skip
    # the listener's transport, topic and domain: the convoy file's; the forger's: flags
    listen = [*BSM, "listen", "--iface", "oc0", "--convoy", str(convoy), "--count", "8",
              "--timeout", "30"]  # fmt: skip
    signed = [*send, "--convoy", str(convoy), "--key", str(keys / "vehicle-1.key")]
    unsigned = [*send, "--transport", "ros2", "--ros2-topic", "/lab/v2v", "--ros2-domain", "5",
                "--count", "3"]  # fmt: skip
    heard, member, forger = run_in_netns(
        [listen, after(3.0, signed), after(5.0, unsigned)], timeout=50
    )
    for p in (heard, member, forger):
        assert p.returncode == 0, p.stderr
    assert "to ROS 2 topic /lab/v2v (DDS domain 5)" in member.stderr
    lines = heard.stdout.strip().splitlines()
    accepted = [ln for ln in lines if ln.startswith("[lab.vehicle-1] id=")]
    assert len(accepted) == 5, lines
    for k, line in enumerate(accepted):
        f = _fields(line)
        assert (f["id"], f["cnt"], f["speed"]) == (DEFAULT_SEND_ID.hex().upper(), str(k), "3.00")
        east, north = _enu(line)  # 3 m/s north
        assert abs(east) < 0.02 and 0.3 * k - 0.02 <= north <= 0.3 * k + 1.5, (k, east, north)
    anon = f"id {DEFAULT_SEND_ID.hex().upper()} (unsigned)"
    assert lines.count(f"REJECTED unsigned: {anon}") == 3
    assert lines[-3:] == [  # the summary, senders sorted by name
        f"{anon}: accepted 0, rejected 3 (unsigned=3)",
        "lab.vehicle-1: accepted 5, rejected 0",
        "summary: 5 accepted, 3 rejected from 2 senders",
    ]


_WAIT = """
import json, os, time
from openconvoy.comms.dds import DdsTransport
link = DdsTransport(os.environ["OPENCONVOY_NETNS_IFACE"], domain_id=9)
cpu, wall = time.thread_time(), time.monotonic()
idle = link.wait(1.0)
cpu, wall = time.thread_time() - cpu, time.monotonic() - wall
link.send(b"one")  # our own reader hears our writer (Cyclone delivers locally)
woke = link.wait(10.0)
got = [d.data.decode() for d in link.recv_all()]
drained = link.wait(0.05)
# a send-only transport (bsm send's) has no reader for other senders to count
sender = DdsTransport(os.environ["OPENCONVOY_NETNS_IFACE"], domain_id=9, read=False)
matched = [sender.wait_for_readers(10.0), link.wait_for_readers(0.5)]
sender.send(b"two")
link.wait(10.0)
got += [d.data.decode() for d in link.recv_all()] + [len(sender.recv_all())]
sender.close()
link.close()
try:
    link.wait(0.1)
    closed = "no error"
except OSError as exc:
    closed = str(exc)
print(json.dumps([idle, cpu, wall, woke, got, drained, matched, closed]))
"""


@pytest.mark.netns
def test_dds_transport_wait_blocks_until_a_sample_without_spinning_and_send_only_has_no_reader():
    (r,) = run_in_netns([[sys.executable, "-c", _WAIT]], timeout=40)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    idle, cpu, wall, woke, got, drained, matched, closed = out
    assert idle is False and wall >= 0.99  # it waited the timeout out ...
    assert cpu < 0.2, cpu  # ... asleep: a polling loop would burn about `wall` of CPU
    assert woke is True and drained is False
    assert got == ["one", "two", 0]  # its own sample, the send-only one's; that one reads none
    assert matched == [1, 0]
    assert closed == "V2V DDS participant closed"


@pytest.mark.netns
def test_a_multicast_convoy_file_gives_the_group_and_port(tmp_path):
    convoy = tmp_path / "lab.toml"
    convoy.write_text(
        '[convoy]\nname = "lab"\n[v2v]\nauth = "off"\ngroup = "ff15::4f44"\nport = 4201\n'
    )
    send = [*BSM, "send", "--iface", "oc0", "--convoy", str(convoy), "--count", "3", "--rate", "20"]
    heard, default_group, sender = run_in_netns(
        [
            [
                *BSM,
                "listen",
                "--iface",
                "oc0",
                "--group",
                "ff15::4f44",
                "--port",
                "4201",
                "--count",
                "3",
                "--timeout",
                "20",
            ],  # fmt: skip
            [*BSM, "listen", "--iface", "oc0", "--timeout", "8"],
            after(2.0, send),
        ],
        timeout=30,
    )
    assert sender.returncode == 0, sender.stderr
    assert "sent 3 BSMs on oc0 to [ff15::4f44]:4201" in sender.stderr
    assert heard.returncode == 0 and default_group.returncode == 0, heard.stderr
    assert [_fields(ln)["cnt"] for ln in heard.stdout.splitlines()] == ["0", "1", "2"]
    assert default_group.stdout == ""
