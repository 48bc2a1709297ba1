"""``openconvoy demo --link mavros --ros 1|2 | ap-dds | px4-dds``: the three-vehicle demo
through MAVROS stand-ins on a real roscore (Debian's rospy in node processes) and on real
rclpy (Fast DDS, inside the demo's private network namespace), through AP_DDS stand-ins
(rclpy), and through PX4 DDS stand-ins (real Cyclone DDS on the namespace's loopback),
against the MAVLink demo of the same vehicles, scenario and seed; the deploys' ``--bag`` bags hold what their CSV logs hold, and the V2V bytes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from openconvoy.bag import read_bag
from openconvoy.comms.netns import netns_unavailable_reason
from openconvoy.logs import read_log
from openconvoy.testing import same

DURATION_S = 30.0


def _demo(out: Path, *extra: str) -> dict:
    r = subprocess.run(
        [sys.executable, "-m", "openconvoy.cli", "demo", "--json", "--duration", str(DURATION_S)]
        + ["--out", str(out), *extra],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if r.returncode != 0:
        tails = [
            f"--- {f.name}\n" + "\n".join(f.read_text(errors="replace").splitlines()[-15:])
            for f in sorted(out.glob("deploy_*.txt"))
        ]
        raise AssertionError("\n".join([r.stdout[-3000:], r.stderr[-3000:], *tails]))
    return json.loads(r.stdout.strip().splitlines()[-1])


def _p95_not_10_percent_worse(
    out: Path, link: tuple[str, ...], base: tuple[str, ...]
) -> tuple[dict, dict]:
    """The demo over ``link`` and the MAVLink demo ``base`` (same seed): the link's p95 no
    more than 10 % above MAVLink's. What is judged is what the link costs the convoy, so the
    band is one-sided: a run's p95 is set by its start-up and speed-change transients, whose
    timing the machine moves (two MAVLink runs at load 18-23 differed by 7 %, up to 15 % in other rounds,
    docs/ros.md), and on CI's 2-core machine both ROS links came out 11-17 % *better* than
    their MAVLink pairs (ROS 1 0.295 / 0.280 m against 0.331 / 0.336 m; px4-dds 0.515 /
    0.575 m against 0.634 / 0.658 m), which a two-sided band refused. One pair above the
    band is followed by a second, and the two pairs' summed p95s must then hold it (more
    samples, the same band). The first pair's runs."""
    first = (_demo(out / "link-0", *link), _demo(out / "base-0", *base))
    p95 = [[r["deploy"]["p95_platooning_error_m"] for r in first]]
    if p95[0][0] > 1.10 * p95[0][1]:
        again = (_demo(out / "link-1", *link), _demo(out / "base-1", *base))
        p95.append([r["deploy"]["p95_platooning_error_m"] for r in again])
    linked, based = sum(p[0] for p in p95), sum(p[1] for p in p95)
    assert linked <= 1.10 * based, p95
    return first


@pytest.mark.e2e
@pytest.mark.netns
def test_mavros_ros2_demo_completes(tmp_path: Path) -> None:
    """Completes through rclpy nodes with the convoy kept together. Its p95 against the
    MAVLink demo's is measured by ``benchmarks/bench_demo_ros.py``, not asserted here: on a
    loaded 2-core machine the ROS 2 deploys overran control periods (docs/ros.md gives the
    figures)."""
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    ros = _demo(tmp_path / "ros2", "--link", "mavros", "--ros", "2")
    assert ros["deploy"]["duration_s"] > DURATION_S - 1.0
    assert ros["deploy"]["collisions"] == 0 and ros["deploy"]["min_gap_m"] > 13.0
    for vid in range(3):
        meta = json.loads((tmp_path / "ros2" / "deploy" / f"vehicle_{vid}.json").read_text())
        assert meta["link"] == f"mavros (ROS 2, /vehicle_{vid}/mavros)"


@pytest.mark.e2e
@pytest.mark.netns
def test_ap_dds_demo_completes(tmp_path: Path) -> None:
    """``--link ap-dds``: the deploys drive through AP_DDS's topics and services (their
    nodes Cyclone DDS directly, the AP_DDS stand-ins rclpy) and complete with the convoy kept together; p95 against
    the MAVLink demo is reported in docs/ros.md, not asserted."""
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    ap = _demo(tmp_path / "ap", "--link", "ap-dds")
    assert ap["deploy"]["duration_s"] > DURATION_S - 1.0
    assert ap["deploy"]["collisions"] == 0 and ap["deploy"]["min_gap_m"] > 13.0
    for vid in range(3):
        meta = json.loads((tmp_path / "ap" / "deploy" / f"vehicle_{vid}.json").read_text())
        assert meta["link"] == f"ap-dds (DDS domain 0, /vehicle_{vid}/ap)"  # Cyclone, no ROS


@pytest.mark.e2e
@pytest.mark.netns
def test_mavros_demo_matches_the_mavlink_demo(tmp_path: Path) -> None:
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    ros, _ = _p95_not_10_percent_worse(tmp_path, ("--link", "mavros", "--ros", "1", "--bag"), ())
    assert ros["deploy"]["collisions"] == 0 and ros["deploy"]["min_gap_m"] > 13.0
    deploy = tmp_path / "link-0" / "deploy"
    for vid in range(3):
        meta = json.loads((deploy / f"vehicle_{vid}.json").read_text())
        assert meta["link"] == f"mavros (ROS 1, /vehicle_{vid}/mavros)"
        assert meta["autopilot"] == "ardupilot"
        csv_log = read_log(deploy / f"vehicle_{vid}.csv")
        bag_log = read_bag(deploy / f"vehicle_{vid}_bag")
        assert list(bag_log) == list(csv_log) and len(csv_log["t_s"]) > 10 * DURATION_S
        assert not [c for c in csv_log if not same(csv_log[c], bag_log[c])], vid
    # V2V bytes: the leader's sent datagrams in its bag.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap_file,) = (deploy / "vehicle_0_bag").glob("*.mcap")
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        tx = [
            bytes(m.data)
            for _, _, _, m in reader.iter_decoded_messages(topics=["/vehicle_0/v2v/tx"])
        ]
    meta0 = json.loads((deploy / "vehicle_0.json").read_text())
    # The demo signs its V2V (it fails closed without keys): each datagram an IEEE 1609.2
    # SPDU, the BSMs under their PSID, then the leader's "scenario complete" ones.
    from openconvoy.comms.security import spdu as sp
    from openconvoy.comms.security.certs import PSID_BSM, PSID_COMPLETE

    spdus = [sp.decode_signed(d) for d in tx]
    bsms = [s for s in spdus if s.psid == PSID_BSM]
    assert len(bsms) == meta0["v2v_counters"]["sent"] > 0
    assert all(s.payload[:2] == b"\x00\x14" for s in bsms)
    assert {s.psid for s in spdus} <= {PSID_BSM, PSID_COMPLETE}


@pytest.mark.e2e
@pytest.mark.netns
def test_px4dds_demo_matches_the_mavlink_demo(tmp_path: Path) -> None:
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    dds, _ = _p95_not_10_percent_worse(
        tmp_path, ("--autopilot", "px4", "--link", "px4-dds"), ("--autopilot", "px4")
    )
    assert dds["deploy"]["collisions"] == 0 and dds["deploy"]["min_gap_m"] > 13.0
    for vid in range(3):
        meta = json.loads((tmp_path / "link-0" / "deploy" / f"vehicle_{vid}.json").read_text())
        assert meta["link"] == f"px4-dds (domain 0, ns vehicle_{vid})"
        assert meta["autopilot"] == "px4"
        assert meta["overruns"] <= meta["ticks"] * 0.05


@pytest.mark.e2e
@pytest.mark.netns
def test_mixed_links_demo_takes_each_link_from_the_convoy_file(tmp_path: Path) -> None:
    """``--link mavlink,mavros-ros1,ap-dds``: the demo writes a ``[[vehicle]]`` table per
    vehicle, starts the stand-ins those links need (a roscore and a MAVROS stand-in for
    vehicle 1, an AP_DDS stand-in on ROS 2 for vehicle 2), and each deploy, given no
    ``--link``, drives its vehicle through its table's link; the convoy stays together."""
    from openconvoy.convoy import load_convoy

    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    run = _demo(tmp_path / "mixed", "--link", "mavlink,mavros-ros1,ap-dds")
    convoy = load_convoy(tmp_path / "mixed" / "convoy.toml")
    assert [(v.link, v.ros, v.ns) for v in convoy.vehicle] == [
        ("mavlink", 1, ""),
        ("mavros", 1, "/vehicle_1/mavros"),
        ("ap-dds", 1, "/vehicle_2/ap"),
    ]
    links = [
        json.loads((tmp_path / "mixed" / "deploy" / f"vehicle_{vid}.json").read_text())["link"]
        for vid in range(3)
    ]
    assert links == [
        "mavlink",
        "mavros (ROS 1, /vehicle_1/mavros)",
        "ap-dds (DDS domain 0, /vehicle_2/ap)",  # Cyclone DDS, the default
    ]
    assert run["deploy"]["duration_s"] > DURATION_S - 1.0
    assert run["deploy"]["collisions"] == 0 and run["deploy"]["min_gap_m"] > 13.0
