"""V2V over ROS 2 (``comms.dds``): the signed BSM bytes on a ROS 2 topic through Cyclone DDS,
read by a real rclpy node, and garbage and replays from the topic counted and dropped."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import pytest

from openconvoy.comms import bsm as j
from openconvoy.comms.dds import dds_topic, interface_config
from openconvoy.comms.netns import run_in_netns
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.certs import PSID_BSM
from openconvoy.comms.tempids import derive_temp_id
from openconvoy.core.errors import ConfigError

DRIVER = Path(__file__).with_name("dds_v2v_driver.py")


def test_ros_topic_names_map_to_dds_names_and_bad_ones_are_refused():
    assert dds_topic("/openconvoy/v2v") == "rt/openconvoy/v2v"
    assert dds_topic("/lab_2/v2v") == "rt/lab_2/v2v"
    for bad in ("openconvoy/v2v", "/2lab/v2v", "/a//b", "/a b", "/"):
        with pytest.raises(ConfigError, match="ROS 2 topic name"):
            dds_topic(bad)
    assert "<NetworkInterface name='oc0'/>" in interface_config("oc0")
    with pytest.raises(ConfigError):
        interface_config("x'/><Peers")


@pytest.mark.netns
@pytest.mark.e2e
def test_rclpy_reads_our_signed_bsms_and_garbage_and_replays_are_dropped(tmp_path):
    keys = tmp_path / "lab.keys"
    now = time.time()
    ks.init_authority(keys, "lab", now)
    for i in range(3):
        ks.issue_vehicle(keys, "lab", i, now)
    (run,) = run_in_netns([[sys.executable, str(DRIVER), str(keys)]], timeout=90)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    # vehicle 1 heard vehicle 0 over DDS, verified, as over multicast
    assert len(out["got"]) >= 10
    assert {g["sender"] for g in out["got"]} == {0}
    assert all(math.isclose(g["speed"], 1.25, abs_tol=0.02) for g in out["got"])
    # the rclpy node saw the same signed bytes: decoded with our decoders
    lab0 = derive_temp_id("lab", 0)
    genuine = [m for m in out["heard"] if m["vehicle_id"] == 0 and m["direction"] == "tx"]
    assert len(genuine) >= 10
    for m in genuine[:10]:
        spdu = sp.decode_signed(bytes.fromhex(m["data"]))
        assert spdu.psid == PSID_BSM
        frame = j.decode_frame(spdu.payload)
        assert frame.core.temp_id == lab0
        assert j.to_physical(frame.core)["speed_mps"] == pytest.approx(1.25, abs=0.02)
    # garbage (3 frames, one empty) counted malformed, the replay rejected; nothing delivered
    c = out["counters"]
    assert c["malformed"] == 3 and out["late"] == 0 and out["bad_samples"] == 0
    assert c["rejected"] == 1 and out["auth"]["duplicate"] + out["auth"]["stale"] == 1
    assert out["abort"][0] == 0, out["abort"]
    assert "abort sent on oc0 (6 datagrams, signed by lab.authority)" in out["abort"][1]
    assert out["abort"][2] == [
        -1,
        -1,
        -1,
    ]  # the operator's abort on DDS, each repeat heard (3 on multicast too)
    assert c["aborts"] == 3 and c["received"] == len(out["got"]) + 3
    assert c["datagrams"] == c["received"] + 4


def test_link_config_checks_the_transport_and_the_topic():
    from openconvoy.comms.v2v import LinkConfig

    with pytest.raises(ConfigError, match="ROS 2 topic name"):
        LinkConfig("oc0", transport="ros2", ros2_topic="v2v")
    with pytest.raises(ConfigError, match="not one of multicast, ros2"):
        LinkConfig("oc0", transport="udp")


_CLASH = """
import os
from openconvoy.bridge.px4dds.dds import Participant
from openconvoy.comms.dds import DdsTransport
from openconvoy.core.errors import LinkError
Participant(0, localhost=True)
try:
    DdsTransport(os.environ["OPENCONVOY_NETNS_IFACE"])
except LinkError as exc:
    print(exc)
print(DdsTransport(os.environ["OPENCONVOY_NETNS_IFACE"], domain_id=1).topic)
"""


@pytest.mark.netns
def test_a_domain_clash_with_px4_dds_on_loopback_is_one_line_naming_the_way_out():
    (r,) = run_in_netns([[sys.executable, "-c", _CLASH]], timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    first, second = r.stdout.strip().splitlines()
    assert first.startswith("cannot use DDS domain 0 on oc0 for V2V topic /openconvoy/v2v")
    assert "ros2_domain another id" in first
    assert second == "/openconvoy/v2v"  # another domain id works
