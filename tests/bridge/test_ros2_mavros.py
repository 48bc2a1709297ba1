"""The MAVROS link over ROS 2: real rclpy (PyPI's Jazzy wheels, Fast DDS) in node processes
inside a private network namespace, our ``mavros_msgs`` built with rosidl, the MAVROS
stand-in forwarding to the simulated ArduPilot over real MAVLink."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from openconvoy.bridge.ros.mavros_link import MavrosLink
from openconvoy.bridge.ros.mavros_standin import MavrosStandIn
from openconvoy.bridge.ros.ros1 import MSG_DIR
from openconvoy.bridge.ros.ros2 import LoopbackNetns, Ros2Node, qos_for, type_hashes
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.testing import free_port, wait_for

MAVROS_2 = Path(__file__).resolve().parents[1] / "data" / "ros" / "mavros-2.12.0"


@pytest.fixture(scope="module")
def netns() -> Iterator[LoopbackNetns]:
    with LoopbackNetns() as ns:
        yield ns


@pytest.fixture(scope="module")
def mavros_2_hashes() -> dict[str, str]:
    return type_hashes(MAVROS_2)


def test_our_mavros_msgs_have_mavros_2_type_hashes(mavros_2_hashes: dict[str, str]) -> None:
    """rosidl's RIHS01 hashes (fields and nested types; constants and comments do not count)
    of the text we ship equal those of MAVROS 2.12.0's ``mavros_msgs`` for every interface
    we use, so a real MAVROS 2 and our nodes agree on the types."""
    ours = type_hashes(MSG_DIR)
    names = {
        "mavros_msgs/msg/State",
        "mavros_msgs/msg/PositionTarget",
        "mavros_msgs/msg/GlobalPositionTarget",
        "mavros_msgs/srv/SetMode",
        "mavros_msgs/srv/CommandBool",
    }
    # (and each service's Request, Response and Event types)
    assert names <= set(ours) and len(ours) == 3 + 2 * 4
    assert ours == mavros_2_hashes
    assert all(h.startswith("RIHS01_") and len(h) == 7 + 64 for h in ours.values())
    # MAVROS 2's State carries mode-name constants ours lacks: the text differs, the type not.
    assert (MAVROS_2 / "msg" / "State.msg").read_text() != (
        MSG_DIR / "msg" / "State.msg"
    ).read_text()


def test_qos_follows_mavros_2() -> None:
    assert qos_for("/vehicle_1/mavros/state") == "state"
    for topic in ("global_position/global", "imu/data", "setpoint_raw/global", "estate"):
        assert qos_for(f"/mavros/{topic}") == "sensor"


def test_link_drives_the_vehicle_over_dds(
    netns: LoopbackNetns, mavros_2_hashes: dict[str, str]
) -> None:
    """Discovery sees the stand-in's ``state`` with MAVROS 2's type hash and QoS (reliable,
    transient local) and its sensor topics best effort; a third rclpy node hears our
    setpoints with the fields MAVROS turns into ArduPilot's SET_POSITION_TARGET_GLOBAL_INT
    (ENU velocity (0, speed, 0): NED vx = the body-forward speed; yaw = the ENU heading);
    the simulated vehicle drives at that heading."""
    port = free_port()
    vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", SimVehicleConfig(ready_after_s=0.0)).start()
    standin = MavrosStandIn(
        Ros2Node("/dds_mavros", netns_pid=netns.pid), f"udpout:127.0.0.1:{port}", "/v9/mavros"
    ).start()
    link = MavrosLink(
        lambda: Ros2Node("/dds_link", netns_pid=netns.pid),
        "/v9/mavros",
        DEFAULT_HOME,
        9,
        "ardupilot",
    )
    spy = Ros2Node("/dds_spy", netns_pid=netns.pid)
    heard: list[dict] = []
    try:
        spy.subscribe(
            "/v9/mavros/setpoint_raw/global", "mavros_msgs/GlobalPositionTarget", heard.append
        )
        link.connect(20.0)
        # The spy discovers the stand-in on its own (DDS discovery is per participant).
        assert wait_for(lambda: len(spy.publishers("/v9/mavros/state")) == 1, 10.0)
        assert wait_for(lambda: len(spy.publishers("/v9/mavros/global_position/global")) == 1, 10.0)
        (state_pub,) = spy.publishers("/v9/mavros/state")
        assert state_pub["node"] == "/dds_mavros"
        assert state_pub["type"] == "mavros_msgs/msg/State"
        assert state_pub["type_hash"] == mavros_2_hashes["mavros_msgs/msg/State"]
        assert (state_pub["reliability"], state_pub["durability"]) == (
            "RELIABLE",
            "TRANSIENT_LOCAL",
        )
        (fix_pub,) = spy.publishers("/v9/mavros/global_position/global")
        assert fix_pub["reliability"] == "BEST_EFFORT"
        link.modes.prepare_and_arm(20.0)
        heading = math.radians(60.0)

        def moving() -> bool:
            tel = link.poll()
            link.setpoints.send(1.5, heading)
            return tel is not None and tel.state.speed > 1.0

        assert wait_for(moving, 15.0)
        assert wait_for(lambda: moving() and abs(vehicle.state().heading - heading) < 0.1, 10.0)

        # The spy's subscription may match the link's publisher late (discovery under
        # load): keep the setpoints coming while waiting for it to hear them.
        def heard_some() -> bool:
            moving()  # one more setpoint
            return len(heard) > 5

        assert wait_for(heard_some, 15.0)
        m = heard[-1]
        assert m["coordinate_frame"] == 6 and m["type_mask"] == 2503
        assert m["velocity"]["x"] == 0.0 and m["velocity"]["y"] == pytest.approx(1.5)
        assert m["yaw"] == pytest.approx(heading, abs=1e-6)
        assert abs(m["header"]["stamp"] - time.time()) < 5.0
        assert standin.setpoints_forwarded > 10
    finally:
        spy.close()
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()


def test_px4_over_dds(netns: LoopbackNetns) -> None:
    """PX4 behind MAVROS 2: told by its boot mode (AUTO.LOITER), OFFBOARD and armed after a
    setpoint stream (``setpoint_raw/local``), drives at the commanded heading."""
    port = free_port()
    vehicle = SimVehicle(
        f"udpin:127.0.0.1:{port}", SimVehicleConfig(autopilot="px4", ready_after_s=0.0)
    ).start()
    standin = MavrosStandIn(
        Ros2Node("/px4_mavros", netns_pid=netns.pid), f"udpout:127.0.0.1:{port}", "/p4/mavros"
    ).start()
    link = MavrosLink(
        lambda: Ros2Node("/px4_link", netns_pid=netns.pid), "/p4/mavros", DEFAULT_HOME, 4
    )
    try:
        link.connect(20.0)
        assert link.autopilot == "px4"
        link.modes.prepare_and_arm(20.0)
        heading = math.radians(30.0)
        seen = []

        def moving() -> bool:
            tel = link.poll()
            link.setpoints.send(1.5, heading)
            if tel is not None:
                seen.append(tel)
            return tel is not None and tel.mode == "OFFBOARD" and tel.state.speed > 0.8

        assert wait_for(moving, 15.0)
        assert wait_for(lambda: moving() and abs(seen[-1].state.heading - heading) < 0.2, 10.0)
        assert seen[-1].armed
    finally:
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()
