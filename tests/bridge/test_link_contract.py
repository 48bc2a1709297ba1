"""The ``VehicleLink`` contract: what the runner relies on, held for every link — the
MAVLink one against a simulated vehicle (real MAVLink bytes over localhost UDP), the ideal
one, the MAVROS one over ROS 1 (a real roscore, Debian's rospy in node processes, the
MAVROS stand-in forwarding to the simulated vehicle over real MAVLink) and over ROS 2 (real
rclpy and Fast DDS in node processes inside a private network namespace), and the px4-dds
one (real Cyclone DDS on the loopback interface, PX4's DDS stand-in forwarding to the
simulated PX4 over real MAVLink), and the ap-dds one (real rclpy in a private network
namespace, the AP_DDS stand-in forwarding to the simulated ArduPilot over real MAVLink),
both with an rclpy node and with a Cyclone DDS one (no ROS, ``ap-dds-cyclone``: on the
namespace's veth, where Cyclone and the stand-in's Fast DDS find each other)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import pytest

from openconvoy.bridge.ideallink import IdealLink
from openconvoy.bridge.link import Modes, Setpoints, Telemetry, VehicleLink
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.px4dds.link import Px4DdsLink
from openconvoy.bridge.px4dds.standin import Px4DdsStandIn
from openconvoy.bridge.ros.apdds_link import ApDdsLink
from openconvoy.bridge.ros.apdds_standin import ApDdsStandIn
from openconvoy.bridge.ros.mavros_link import MavrosLink
from openconvoy.bridge.ros.mavros_standin import MavrosStandIn
from openconvoy.bridge.ros.ros1 import Ros1Node, Roscore
from openconvoy.bridge.ros.ros2 import CycloneNode, LoopbackNetns, Ros2Node
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.comms.netns import IFACE
from openconvoy.testing import free_port, wait_for

DECLARED = (
    "telemetry_timeout_s",
    "heartbeat_timeout_s",
    "telemetry_rates",
    "setpoints",
    "modes",
    "autopilot",
    "lost",
    "connect",
    "poll",
    "reconnect",
    "close",
)
"""What the runner reads of a link: the connection and its telemetry, and two capabilities."""
CAPABILITIES = {
    "setpoints": (Setpoints, ("send", "stop")),
    "modes": (
        Modes,
        (
            "pilot_took_over",
            "takeover_reason",
            "failsafe_took_over",
            "prepare_and_arm",
            "hold",
            "disarm",
        ),
    ),
}


@pytest.fixture(scope="module")
def roscore() -> Iterator[Roscore]:
    with Roscore() as core:
        yield core


@pytest.fixture(scope="module")
def ros2_netns() -> Iterator[LoopbackNetns]:
    with LoopbackNetns() as ns:
        yield ns


@pytest.fixture(scope="module")
def veth_netns() -> Iterator[LoopbackNetns]:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")  # Fast DDS looks on the veth
        with LoopbackNetns(veth=True) as ns:
            yield ns


LINKS = ["mavlink", "ideal", "mavros-ros1", "mavros-ros2", "px4-dds", "ap-dds", "ap-dds-cyclone"]


@pytest.fixture(params=LINKS)
def link(request) -> Iterator[VehicleLink]:
    if request.param == "ideal":
        yield IdealLink(time.monotonic, time.time, DEFAULT_HOME, vehicle_id=1, x=3.0, y=-4.0)
        return
    port = free_port()
    vehicle = SimVehicle(
        f"udpin:127.0.0.1:{port}",
        SimVehicleConfig(
            autopilot="px4" if request.param == "px4-dds" else "ardupilot",
            ready_after_s=0.0,
            start_x_m=3.0,
            start_y_m=-4.0,
        ),
    ).start()
    if request.param == "px4-dds":
        ns = f"contract_{port}"  # a namespace per test: no samples from an earlier one
        px4 = Px4DdsStandIn(f"udpout:127.0.0.1:{port}", ns=ns, localhost=True).start()
        dds_link = Px4DdsLink(ns, DEFAULT_HOME, 1, localhost=True)
        try:
            yield dds_link
        finally:
            dds_link.close()
            px4.stop()
            vehicle.stop()
        return
    if request.param.startswith("ap-dds"):
        cyclone = request.param == "ap-dds-cyclone"
        pid = request.getfixturevalue("veth_netns" if cyclone else "ros2_netns").pid

        def make() -> Ros2Node:
            if cyclone:
                return CycloneNode("/contract_ap_link", netns_pid=pid, iface=IFACE)
            return Ros2Node("/contract_ap_link", netns_pid=pid)

        ap = ApDdsStandIn(
            Ros2Node("/contract_ap_dds", netns_pid=pid), f"udpout:127.0.0.1:{port}", "/v1/ap"
        ).start()
        first = [make()]  # started early, as above

        def ap_node() -> Ros2Node:
            return first.pop() if first else make()

        ap_link = ApDdsLink(ap_node, "/v1/ap", DEFAULT_HOME, 1)
        try:
            yield ap_link
        finally:
            ap_link.close()
            ap.stop()
            ap.node.close()
            vehicle.stop()
        return
    if request.param.startswith("mavros-"):
        if request.param == "mavros-ros1":
            core = request.getfixturevalue("roscore")
            mavros_node = Ros1Node("/contract_mavros", core.uri)

            def node() -> Ros1Node:
                return Ros1Node("/contract_link", core.uri)
        else:
            pid = request.getfixturevalue("ros2_netns").pid
            mavros_node = Ros2Node("/contract_mavros", netns_pid=pid)
            # The link's first node is started here, as a vehicle's ROS 2 process is before
            # it connects (rclpy's start-up in a busy CI is seconds); reconnect starts anew.
            started = [Ros2Node("/contract_link", netns_pid=pid)]

            def node() -> Ros1Node:
                return started.pop() if started else Ros2Node("/contract_link", netns_pid=pid)

        standin = MavrosStandIn(mavros_node, f"udpout:127.0.0.1:{port}", "/v1/mavros").start()
        ros_link = MavrosLink(node, "/v1/mavros", DEFAULT_HOME, 1, "ardupilot")
        try:
            yield ros_link
        finally:
            ros_link.close()
            standin.stop()
            standin.node.close()
            vehicle.stop()
        return
    mav = MavlinkLink(
        f"udpout:127.0.0.1:{port}", DEFAULT_HOME, vehicle_id=1, on_status=lambda line: None
    )
    try:
        yield mav
    finally:
        mav.close()
        vehicle.stop()


def _telemetry(link: VehicleLink, timeout: float = 3.0) -> Telemetry:
    got: list[Telemetry] = []

    def fresh() -> bool:
        tel = link.poll()
        if tel is not None:
            got.append(tel)
        return bool(got)

    assert wait_for(fresh, timeout)
    return got[-1]


def test_every_declared_member_is_there_and_nothing_else_is_read(link: VehicleLink) -> None:
    link.connect(5.0)  # ``autopilot`` is known only once connected
    assert isinstance(link, VehicleLink)
    for name in DECLARED:
        assert hasattr(link, name), name
    # The protocols declare exactly what the runner uses: the lists above.
    assert _declared(VehicleLink) == set(DECLARED)
    for name, (protocol, members) in CAPABILITIES.items():
        capability = getattr(link, name)
        assert isinstance(capability, protocol), name
        assert _declared(protocol) == set(members), name
        for member in members:
            assert hasattr(capability, member), f"{name}.{member}"


def _declared(protocol: type) -> set[str]:
    """The public names a protocol declares (methods, properties and annotations)."""
    names = {n for n in dir(protocol) if not n.startswith("_")}
    return names | set(getattr(protocol, "__annotations__", {}))


def test_connect_telemetry_arm_drive_stop_hold_close(link: VehicleLink) -> None:
    link.connect(5.0)
    assert not link.lost and link.autopilot in ("ardupilot", "px4")
    assert link.telemetry_rates and all(r > 0 for r in link.telemetry_rates.values())
    assert link.telemetry_timeout_s > 0 and link.heartbeat_timeout_s > 0
    tel = _telemetry(link)
    assert tel.state.vehicle_id == 1
    assert tel.state.x == pytest.approx(3.0, abs=0.05) and tel.state.y == pytest.approx(
        -4.0, abs=0.05
    )
    assert abs(tel.state.t - time.time()) < 1.0  # stamped on the wall clock
    assert (
        not link.modes.pilot_took_over
        and link.modes.takeover_reason == ""
        and not link.modes.failsafe_took_over
    )
    link.modes.prepare_and_arm(10.0)
    assert _telemetry(link).armed
    assert link.setpoints.send(1.0, math.radians(10.0))
    assert wait_for(lambda: (t := link.poll()) is not None and t.state.speed > 0.3, 5.0)
    assert link.setpoints.stop()
    assert wait_for(lambda: (t := link.poll()) is not None and abs(t.state.speed) < 0.05, 8.0)
    link.modes.hold(3.0)
    assert wait_for(lambda: (t := link.poll()) is not None and t.mode in ("HOLD", "LOITER"), 3.0)
    link.modes.disarm(3.0)
    assert wait_for(lambda: (t := link.poll()) is not None and not t.armed, 3.0)
    link.close()
    link.close()  # idempotent
    assert link.lost
