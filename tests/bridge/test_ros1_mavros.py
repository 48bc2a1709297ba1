"""MAVROS over ROS 1: our ``mavros_msgs`` subset is MAVROS's (equal MD5 sums), MAVROS's frame
conversions (``ftf``), and what the simulated ArduPilot does with each setpoint topic —
through a real roscore, Debian's rospy in node processes and the MAVROS stand-in."""

from __future__ import annotations

import math
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from openconvoy.bridge.ros import ftf
from openconvoy.bridge.ros.mavros_link import MavrosLink
from openconvoy.bridge.ros.mavros_standin import MavrosStandIn, custom_mode_of, mode_name
from openconvoy.bridge.ros.ros1 import MSG_DIR, Ros1Node, Roscore, system_python
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.testing import free_port, wait_for

MAVROS_1_21 = Path(__file__).resolve().parents[1] / "data" / "ros" / "mavros-1.21.0"

# MAVROS Noetic's sums (ROS 1 MD5 of the message text; issue 25 measured the prefixes on
# builds of MAVROS 1.x; PositionTarget and GlobalPositionTarget as genpy computes them from
# MAVROS 1.4.0's text, the same in every 1.x release since).
MAVROS_MD5 = {
    "mavros_msgs/State": "ce783f756cab1193cb71ba9e90fece50",
    "mavros_msgs/SetMode": "e4f18fa93379f9ff1780d270ce110203",
    "mavros_msgs/CommandBool": "e09abbb4e5bae6b558e5010966eb6e9e",
    "mavros_msgs/PositionTarget": "dedb0081aaf8cb20209737746bb49117",
}


@pytest.fixture(scope="module")
def roscore() -> Iterator[Roscore]:
    with Roscore() as core:
        yield core


def test_our_mavros_msgs_have_mavros_md5_sums(roscore: Roscore) -> None:
    node = Ros1Node("/md5_check", roscore.uri)
    try:
        got = {t: node.md5(t) for t in MAVROS_MD5}
        assert node.md5("mavros_msgs/GlobalPositionTarget") == node.md5(
            "mavros_msgs/GlobalPositionTarget"
        )
    finally:
        node.close()
    assert got == MAVROS_MD5


def test_mavros_1_5_state_differs_only_by_its_constants() -> None:
    """MAVROS >= 1.5 added mode-name constants to State.msg: another MD5 sum (docs/ros.md)."""
    script = (
        "import sys, genmsg, genmsg.msg_loader as ml, genmsg.gentools as gt\n"
        "ctx = genmsg.MsgContext.create_default()\n"
        "spec = ml.load_msg_from_file(ctx, sys.argv[1], 'mavros_msgs/State')\n"
        "ml.load_depends(ctx, spec, {'std_msgs': ['/usr/share/std_msgs/msg']})\n"
        "print(gt.compute_md5(ctx, spec))\n"
    )
    sums = [
        subprocess.run(
            [system_python(), "-c", script, str(f)], capture_output=True, text=True, check=True
        ).stdout.strip()
        for f in (MSG_DIR / "msg" / "State.msg", MAVROS_1_21 / "msg" / "State.msg")
    ]
    assert sums == [MAVROS_MD5["mavros_msgs/State"], "65cd0a9fff993b062b91e354554ec7e9"]
    ours = (MSG_DIR / "msg" / "State.msg").read_text().split()
    new = (MAVROS_1_21 / "msg" / "State.msg").read_text().splitlines()
    assert " ".join(line for line in new if not line.startswith("string MODE_")).split() == ours


def test_the_link_hears_a_mavros_1_21_state(roscore: Roscore) -> None:
    """A MAVROS >= 1.5 publishes State with another MD5 sum: a plain subscriber with our
    (1.4.0) definition is refused, the link's MD5-agnostic one decodes it (same bytes)."""
    mavros = Ros1Node("/mavros_1_21", roscore.uri, msg_dir=MAVROS_1_21)
    ours = Ros1Node("/ours_1_4", roscore.uri)
    strict = Ros1Node("/ours_1_4_strict", roscore.uri)
    plain: list[dict] = []
    agnostic: list[dict] = []
    try:
        assert mavros.md5("mavros_msgs/State") == "65cd0a9fff993b062b91e354554ec7e9"
        strict.subscribe("/m/state", "mavros_msgs/State", plain.append)
        ours.subscribe("/m/state", "mavros_msgs/State", agnostic.append, any_md5=True)
        mavros.advertise("/m/state", "mavros_msgs/State")

        def heard() -> bool:
            mavros.publish("/m/state", {"connected": True, "armed": True, "mode": "GUIDED"})
            return len(agnostic) >= 3

        assert wait_for(heard, 10.0)
    finally:
        mavros.close()
        ours.close()
        strict.close()
    assert agnostic[-1]["mode"] == "GUIDED" and agnostic[-1]["armed"] is True
    assert plain == []  # refused: MD5 mismatch


@pytest.mark.parametrize("yaw_deg", range(-180, 181, 15))
def test_setpoint_yaw_and_attitude_follow_mavros_ftf(yaw_deg: int) -> None:
    yaw = math.radians(yaw_deg)
    want = math.atan2(math.cos(yaw), math.sin(yaw))  # π/2 − yaw, wrapped
    assert (
        ftf.setpoint_yaw_enu_to_ned(yaw) == pytest.approx(want, abs=1e-12)
        or abs(abs(want) - math.pi) < 1e-9
    )
    q = ftf.attitude_ned_to_enu(0.0, 0.0, yaw)
    assert math.cos(ftf.quaternion_get_yaw(q) - want) == pytest.approx(1.0, abs=1e-12)
    assert ftf.transform_frame_enu_ned((1.0, 2.0, 3.0)) == (2.0, 1.0, -3.0)
    assert ftf.yaw_rate_enu_to_ned(0.3) == -0.3
    assert ftf.compass_hdg_to_enu_heading(90.0) == pytest.approx(0.0, abs=1e-12)  # east


def test_mode_names_are_mavros_maps() -> None:
    assert mode_name(3, 15) == "GUIDED" and mode_name(3, 99) == "CMODE(99)"
    assert mode_name(12, 6 << 16) == "OFFBOARD"
    assert mode_name(12, (4 << 16) | (3 << 24)) == "AUTO.LOITER"
    assert custom_mode_of(12, "AUTO.LOITER") == (4 << 16) | (3 << 24)
    assert custom_mode_of(3, "hold") == 4 and custom_mode_of(3, "NOPE") is None


@pytest.mark.e2e
def test_cmd_vel_unstamped_vector_south_reverses_ardupilot(roscore: Roscore) -> None:
    """The paper's topic with an ENU velocity vector: MAVROS sends type_mask 1479 in
    LOCAL_NED with NED vx = the north component; ArduPilot Rover takes vx's sign as the
    direction, so a vehicle facing south and told "1 m/s south" backs up northwards. Our
    link's setpoint_raw (2503, body-forward speed in NED vx) drives it forward, south."""
    port = free_port()
    vehicle = SimVehicle(
        f"udpin:127.0.0.1:{port}",
        SimVehicleConfig(ready_after_s=0.0, start_heading_rad=-math.pi / 2),
    ).start()
    standin = MavrosStandIn(
        Ros1Node("/rev_mavros", roscore.uri), f"udpout:127.0.0.1:{port}", "/rev/mavros"
    ).start()
    link = MavrosLink(
        lambda: Ros1Node("/rev_link", roscore.uri), "/rev/mavros", DEFAULT_HOME, 1, "ardupilot"
    )
    paper = Ros1Node("/rev_paper", roscore.uri)
    try:
        link.connect(10.0)
        link.modes.prepare_and_arm(15.0)
        paper.advertise("/rev/mavros/setpoint_velocity/cmd_vel_unstamped", "geometry_msgs/Twist")
        time.sleep(0.5)
        y0 = vehicle.state().y

        def drive_paper() -> bool:
            paper.publish(
                "/rev/mavros/setpoint_velocity/cmd_vel_unstamped",
                {"linear": {"x": 0.0, "y": -1.0, "z": 0.0}},
            )
            return vehicle.state().y > y0 + 1.0  # moved north: backwards

        assert wait_for(drive_paper, 10.0)
        assert vehicle.state().speed < -0.5
        assert math.cos(vehicle.state().heading + math.pi / 2) > 0.95  # still facing south
        y1 = vehicle.state().y

        def drive_ours() -> bool:
            link.poll()
            link.setpoints.send(1.0, -math.pi / 2)
            return vehicle.state().y < y1 - 1.0  # moved south: forwards

        assert wait_for(drive_ours, 15.0)
        assert vehicle.state().speed > 0.5
        assert standin.setpoints_forwarded > 20
    finally:
        paper.close()
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()


@pytest.mark.e2e
def test_px4_through_mavros_takeover_and_lost_vehicle(roscore: Roscore) -> None:
    """PX4 behind MAVROS: told by its boot mode, OFFBOARD and armed after a setpoint stream,
    drives; a person's MANUAL latches a takeover (not a failsafe) and stops the setpoints;
    a silent vehicle makes MAVROS report it disconnected (``conn/timeout``): the link is lost."""
    port = free_port()
    vehicle = SimVehicle(
        f"udpin:127.0.0.1:{port}", SimVehicleConfig(autopilot="px4", ready_after_s=0.0)
    ).start()
    standin = MavrosStandIn(
        Ros1Node("/px4_mavros", roscore.uri), f"udpout:127.0.0.1:{port}", "/px4/mavros",
        conn_timeout_s=1.5,
    ).start()  # fmt: skip
    link = MavrosLink(lambda: Ros1Node("/px4_link", roscore.uri), "/px4/mavros", DEFAULT_HOME, 1)
    try:
        link.connect(10.0)
        assert link.autopilot == "px4"  # AUTO.LOITER at boot
        link.modes.prepare_and_arm(15.0)
        heading = math.radians(30.0)
        seen = []

        def moving() -> bool:
            tel = link.poll()
            link.setpoints.send(1.5, heading)
            if tel is not None:
                seen.append(tel)
            return tel is not None and tel.mode == "OFFBOARD" and tel.state.speed > 0.8

        assert wait_for(moving, 10.0)
        assert wait_for(lambda: moving() and abs(seen[-1].state.heading - heading) < 0.2, 10.0)
        vehicle.pilot_set_mode("MANUAL")

        def took_over() -> bool:
            link.poll()
            link.setpoints.send(1.5, heading)
            return link.modes.pilot_took_over

        assert wait_for(took_over, 5.0)
        assert (
            not link.modes.failsafe_took_over and "OFFBOARD -> MANUAL" in link.modes.takeover_reason
        )
        assert not link.setpoints.send(1.5, heading)
        assert not link.lost
        vehicle.freeze()
        assert wait_for(lambda: link.lost, 5.0)
    finally:
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()
