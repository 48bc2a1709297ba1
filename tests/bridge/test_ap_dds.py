"""The ``ap-dds`` link (ArduPilot's AP_DDS ROS 2 interface): real rclpy (PyPI's Jazzy wheels,
Fast DDS) in node processes inside a private network namespace, our ``ardupilot_msgs``
built with rosidl, the AP_DDS stand-in forwarding to the simulated ArduPilot over real
MAVLink."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from openconvoy.bridge.ros.apdds_link import ApDdsLink, yaw_rate_for
from openconvoy.bridge.ros.apdds_standin import ApDdsStandIn, body_forward_speed
from openconvoy.bridge.ros.ros2 import AP_MSG_DIR, LoopbackNetns, Ros2Node, qos_for, type_hashes
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.testing import drive_on_heading, free_port, wait_for

ARDUPILOT_MSGS = Path(__file__).resolve().parents[1] / "data" / "ros" / "ardupilot-msgs"


@pytest.fixture(scope="module")
def netns() -> Iterator[LoopbackNetns]:
    with LoopbackNetns() as ns:
        yield ns


def test_our_ardupilot_msgs_have_ardupilots_type_hashes() -> None:
    """rosidl's RIHS01 hashes of the text we ship equal those of ArduPilot's own
    ``Tools/ros2/ardupilot_msgs`` text for the three interfaces we use."""
    ours = type_hashes(AP_MSG_DIR, pkg="ardupilot_msgs")
    theirs = type_hashes(ARDUPILOT_MSGS, pkg="ardupilot_msgs")
    assert {
        "ardupilot_msgs/msg/Status",
        "ardupilot_msgs/srv/ArmMotors",
        "ardupilot_msgs/srv/ModeSwitch",
    } <= set(ours)
    assert len(ours) == 1 + 2 * 4 and ours == theirs


def test_qos_and_conversions_follow_ap_dds() -> None:
    assert qos_for("/ap/status") == "state"
    for topic in ("navsat", "pose/filtered", "twist/filtered", "cmd_vel"):
        assert qos_for(f"/ap/{topic}") == "sensor"
    # base_link: the body-forward part whatever the yaw; map: ENU projected on the heading.
    for yaw in (0.0, 1.0, -2.5, math.pi):
        m = {"header": {"frame_id": "base_link"}, "twist": {"linear": {"x": -1.2, "y": 0.7}}}
        assert body_forward_speed(m, yaw) == pytest.approx(-1.2)
    m = {"header": {"frame_id": "map"}, "twist": {"linear": {"x": -2.0, "y": 0.0}}}
    assert body_forward_speed(m, -math.pi / 2) == pytest.approx(2.0)  # west-facing, west
    assert body_forward_speed({"header": {"frame_id": "odom"}}, 0.0) is None
    # the heading loop: counter-clockwise (ENU) toward the target, limited, shortest way
    assert yaw_rate_for(0.1, 0.0) == pytest.approx(0.2)
    assert yaw_rate_for(-3.0, 3.0) > 0 and yaw_rate_for(3.0, -3.0) < 0
    assert abs(yaw_rate_for(math.pi / 2, -math.pi / 2)) == pytest.approx(math.radians(120))


def test_spy_sees_cmd_vel_and_vehicle_drives_west(netns: LoopbackNetns) -> None:
    """A third rclpy node subscribed to ``/ap/cmd_vel`` hears our commands: frame
    ``base_link``, linear.x = the speed, angular.z toward the heading; ``/ap/status`` is
    published reliable, transient local with ArduPilot's type hash. Commanded west, the
    simulated rover turns around and drives forwards with x decreasing."""
    port = free_port()
    vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", SimVehicleConfig(ready_after_s=0.0)).start()
    standin = ApDdsStandIn(
        Ros2Node("/ap_standin", netns_pid=netns.pid), f"udpout:127.0.0.1:{port}", "/v7/ap"
    ).start()
    link = ApDdsLink(lambda: Ros2Node("/ap_link", netns_pid=netns.pid), "/v7/ap", DEFAULT_HOME, 7)
    spy = Ros2Node("/ap_spy", netns_pid=netns.pid)
    heard: list[dict] = []
    try:
        spy.subscribe("/v7/ap/cmd_vel", "geometry_msgs/TwistStamped", heard.append)
        link.connect(20.0)
        assert wait_for(lambda: len(spy.publishers("/v7/ap/status")) == 1, 10.0)
        (status_pub,) = spy.publishers("/v7/ap/status")
        assert status_pub["type"] == "ardupilot_msgs/msg/Status"
        assert (
            status_pub["type_hash"]
            == type_hashes(ARDUPILOT_MSGS, pkg="ardupilot_msgs")["ardupilot_msgs/msg/Status"]
        )
        assert (status_pub["reliability"], status_pub["durability"]) == (
            "RELIABLE",
            "TRANSIENT_LOCAL",
        )
        link.modes.prepare_and_arm(20.0)
        driving_west, xs = drive_on_heading(link, math.pi)  # west
        x0 = xs[-1]
        assert wait_for(lambda: driving_west() and xs[-1] < x0 - 1.0, 5.0)
        assert vehicle.state().speed > 1.0  # forwards, not reversing

        # The spy's subscription may match the link's publisher late (discovery under
        # load): keep the setpoints coming while waiting for it to hear them.
        def heard_some() -> bool:
            driving_west()  # one more setpoint
            return len(heard) > 5

        assert wait_for(heard_some, 15.0)
        # On heading the link's yaw-rate loop (gain 2) asks little turning: < 0.2 rad/s is
        # within 0.1 rad of west. Under load a late telemetry can put one command just
        # above, so wait (driving on) for the commands to settle, not for one sample.
        assert wait_for(
            lambda: driving_west() and abs(heard[-1]["twist"]["angular"]["z"]) < 0.2, 5.0
        )
        m = heard[-1]
        assert m["header"]["frame_id"] == "base_link"
        assert abs(m["header"]["stamp"] - time.time()) < 5.0
        assert m["twist"]["linear"] == {"x": pytest.approx(1.5), "y": 0.0, "z": 0.0}
        turning = [h["twist"]["angular"]["z"] for h in heard]
        assert max(abs(r) for r in turning) > 0.5  # it did turn to get there
        assert standin.setpoints_forwarded > 10 and standin.commands_dropped == 0
    finally:
        spy.close()
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()


def test_deploy_makes_the_ap_dds_link_and_refuses_px4() -> None:
    """``deploy --link ap-dds`` builds an ``ApDdsLink`` under ``--ap-ns`` (no node started
    until it connects); with ``--autopilot px4`` it refuses: AP_DDS is ArduPilot's."""
    from dataclasses import replace
    from types import SimpleNamespace

    from openconvoy.bridge.deploy import DeployArgs, _link_name, _make_link
    from openconvoy.core.errors import ConfigError

    preset = SimpleNamespace(length_m=4.5, width_m=1.8)
    a = DeployArgs("paper", 2, "c.toml", None, "lo", link="ap-dds", ap_ns="/vehicle_2/ap")
    link = _make_link(a, DEFAULT_HOME, preset, 20.0, lambda line: None)
    assert isinstance(link, ApDdsLink) and link.ns == "/vehicle_2/ap" and link.lost
    assert link.autopilot == "ardupilot" and link.length_m == 4.5
    assert _link_name(a) == "ap-dds (DDS domain 0, /vehicle_2/ap)"  # Cyclone, the default
    assert _link_name(replace(a, ap_dds_via="rclpy")) == "ap-dds (ROS 2, /vehicle_2/ap)"
    px4 = DeployArgs("paper", 2, "c.toml", None, "lo", link="ap-dds", autopilot="px4")
    with pytest.raises(ConfigError, match="ArduPilot"):
        _make_link(px4, DEFAULT_HOME, preset, 20.0, lambda line: None)
