"""The ``px4-dds`` link through real Cyclone DDS (loopback only) and PX4's DDS stand-in in
front of the simulated PX4: what a plain px4_msgs subscriber sees on
``/fmu/in/trajectory_setpoint``, the direction the rover really drives, PX4's offboard-loss
failsafe when the offboard_control_mode stream stops, and bad input counted and dropped."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from openconvoy.bridge.px4dds import msgs
from openconvoy.bridge.px4dds.dds import (
    IN_QOS,
    LOCALHOST_CONFIG,
    OUT_QOS,
    Participant,
    topic_name,
)
from openconvoy.bridge.px4dds.link import Px4DdsLink, ned_velocity, ned_yaw
from openconvoy.bridge.px4dds.standin import Px4DdsStandIn
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.core.errors import ConfigError
from openconvoy.testing import free_port, wait_for

HERE = Path(__file__).resolve().parent


class Rig:
    """A simulated PX4, its DDS stand-in and a link, on namespace ``ns``."""

    def __init__(self, ns: str) -> None:
        port = free_port()
        self.ns = ns
        self.vehicle = SimVehicle(
            f"udpin:127.0.0.1:{port}",
            SimVehicleConfig(autopilot="px4", ready_after_s=0.0, start_x_m=0.0, start_y_m=0.0),
        ).start()
        self.px4 = Px4DdsStandIn(f"udpout:127.0.0.1:{port}", ns=ns, localhost=True).start()
        self.link = Px4DdsLink(ns, DEFAULT_HOME, 1, localhost=True)

    def close(self) -> None:
        self.link.close()
        self.px4.stop()
        self.vehicle.stop()

    def drive(self, speed: float, heading: float, seconds: float) -> None:
        """Send setpoints at 20 Hz for ``seconds``, polling as the runner does."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.link.setpoints.send(speed, heading)
            self.link.poll()
            time.sleep(0.05)


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(f"t{os.getpid()}_{free_port()}")
    try:
        yield r
    finally:
        r.close()


def test_ned_conversions() -> None:
    # ENU heading 0 = east -> NED (north 0, east v); 90° = north -> (v, 0); yaw NED = 90° - ENU
    assert ned_velocity(2.0, 0.0) == pytest.approx((0.0, 2.0), abs=1e-12)
    assert ned_velocity(2.0, math.pi / 2) == pytest.approx((2.0, 0.0), abs=1e-12)
    assert ned_velocity(2.0, math.pi) == pytest.approx((0.0, -2.0), abs=1e-12)
    assert ned_yaw(0.0) == pytest.approx(math.pi / 2)
    assert ned_yaw(math.pi / 2) == pytest.approx(0.0)
    assert ned_yaw(math.pi) == pytest.approx(-math.pi / 2)


def test_plain_cyclonedds_subscriber_sees_our_setpoints(rig: Rig) -> None:
    env = {**os.environ, "CYCLONEDDS_URI": LOCALHOST_CONFIG}
    sub = subprocess.Popen(
        [sys.executable, str(HERE / "px4dds_subscriber.py"), rig.ns, "6"],
        stdout=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert sub.stdout is not None and sub.stdout.readline().strip() == "ready"
        rig.link.connect(5.0)
        rig.drive(1.5, math.radians(10.0), 1.5)
        rig.drive(2.0, math.radians(180.0), 1.0)
        out, _ = sub.communicate(timeout=15)
    finally:
        sub.kill()
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    sps = [r for r in rows if r["topic"] == "trajectory_setpoint"]
    ocms = [r for r in rows if r["topic"] == "offboard_control_mode"]
    assert len(sps) >= 10 and len(ocms) >= 10
    assert all(r["velocity"] and not r["position"] for r in ocms)
    # the offboard signal comes with every setpoint: far above PX4's 2 Hz minimum
    ts = [r["t"] for r in ocms]
    assert max(b - a for a, b in zip(ts, ts[1:], strict=False)) < 0.5
    first = sps[0]
    # 1.5 m/s at ENU 10° (east by a little north): NED north 1.5·sin 10°, east 1.5·cos 10°
    assert first["velocity"][:2] == pytest.approx([0.2605, 1.4772], abs=1e-3)
    assert math.isnan(first["velocity"][2]) and all(math.isnan(p) for p in first["position"])
    assert first["yaw"] == pytest.approx(math.radians(80.0), abs=1e-5)
    last = sps[-1]
    # 2 m/s west: NED east negative, north 0, yaw -90° (west)
    assert last["velocity"][:2] == pytest.approx([0.0, -2.0], abs=1e-5)
    assert last["yaw"] == pytest.approx(-math.pi / 2, abs=1e-5)


def test_drives_the_way_it_is_told_then_failsafe_on_signal_loss(rig: Rig) -> None:
    link = rig.link
    link.connect(5.0)
    link.modes.prepare_and_arm(10.0)
    assert rig.vehicle.mode == "OFFBOARD" and rig.vehicle.armed
    # what arming's waits read still reaches the runner: its first tick is not stale
    first = link.poll()
    assert first is not None and first.armed and time.monotonic() - first.t_telemetry < 0.2
    rig.drive(1.5, math.radians(180.0), 2.5)  # west: a U-turn from facing east first
    x0, y0 = rig.vehicle.state().x, rig.vehicle.state().y
    rig.drive(1.5, math.radians(180.0), 1.5)
    tel = link.poll() or link._last
    assert tel is not None
    s = rig.vehicle.state()
    assert s.x - x0 < -1.5, "must drive west (ENU x decreasing)"
    assert abs(s.y - y0) < 0.3
    assert s.speed > 0.5 and tel.state.speed > 0.5  # forwards, not backwards
    assert abs(math.remainder(tel.state.heading - math.pi, math.tau)) < math.radians(15)
    assert tel.state.x < -1.0  # the link's ENU agrees with the vehicle's
    # the runner stops (no more offboard_control_mode): PX4's own failsafe after ~1 s
    t_stop = time.monotonic()
    assert wait_for(lambda: link.poll() is not None and link.modes.pilot_took_over, 4.0)
    assert 0.9 < time.monotonic() - t_stop < 3.0
    assert link.modes.failsafe_took_over and "failsafe" in link.modes.takeover_reason
    assert rig.vehicle.mode == "POSCTL" and rig.vehicle.armed
    assert not link.setpoints.send(1.0, 0.0)  # never drives again by itself


def test_bad_input_counted_and_dropped(rig: Rig) -> None:
    link = rig.link
    link.connect(5.0)
    bogus = Participant(0, localhost=True)
    w = bogus.writer(topic_name(rig.ns, "out", msgs.VehicleGlobalPosition), msgs.VehicleGlobalPosition, OUT_QOS)  # fmt: skip
    for _ in range(5):
        w.write(msgs.VehicleGlobalPosition(lat=math.nan, lon=4.0, lat_lon_valid=True))
        w.write(msgs.VehicleGlobalPosition(lat=95.0, lon=4.0, lat_lon_valid=True))
        w.write(msgs.VehicleGlobalPosition(lat=52.0, lon=1e300, lat_lon_valid=True))
        time.sleep(0.02)
    assert wait_for(
        lambda: (link.poll(), link.dropped.get("vehicle_global_position", 0) >= 3)[1], 3.0
    )
    # the link still reads the real vehicle
    assert wait_for(lambda: (t := link.poll()) is not None and abs(t.state.x) < 0.1, 3.0)
    # a setpoint without a velocity (NaN) is dropped by the stand-in, not forwarded
    sw = bogus.writer(topic_name(rig.ns, "in", msgs.TrajectorySetpoint), msgs.TrajectorySetpoint, IN_QOS)  # fmt: skip
    sw.write(msgs.TrajectorySetpoint())
    assert wait_for(lambda: rig.px4.dropped.get("trajectory_setpoint", 0) >= 1, 3.0)
    # a float64 param5 that MAVLink's float32 cannot carry (a disarm, so nothing else happens)
    cw = bogus.writer(topic_name(rig.ns, "in", msgs.VehicleCommand), msgs.VehicleCommand, IN_QOS)
    cw.write(msgs.VehicleCommand(command=msgs.VEHICLE_CMD_COMPONENT_ARM_DISARM, param5=1e300))
    assert wait_for(lambda: rig.px4.dropped.get("vehicle_command", 0) >= 1, 3.0)
    # the bogus writers go away: their readers get Cyclone's InvalidSample (no data), which
    # once killed the stand-in's DDS thread
    bogus.close()
    time.sleep(0.3)
    assert all(th.is_alive() for th in rig.px4._threads)
    assert wait_for(lambda: link.poll() is not None, 2.0)


def test_deploy_cli_makes_a_px4dds_link() -> None:
    from openconvoy.bridge.deploy import DeployArgs, _link_name, _make_link
    from openconvoy.cli import build_parser

    ns = build_parser().parse_args(
        ["deploy", "--policy", "paper", "--vehicle-id", "2", "--convoy", "c.toml"]
        + ["--iface", "lo", "--link", "px4-dds", "--px4-ns", "vehicle_2", "--dds-domain", "7"]
        + ["--dds-localhost"]
    )
    fields = DeployArgs.__dataclass_fields__
    a = DeployArgs(**{k: v for k, v in vars(ns).items() if k in fields})
    link = _make_link(a, DEFAULT_HOME, None, 20.0, lambda line: None)
    assert isinstance(link, Px4DdsLink)
    assert (link.ns, link.domain_id, link.localhost, link.vehicle_id) == ("vehicle_2", 7, True, 2)
    assert link.autopilot == "px4" and link.lost  # nothing opened before connect
    assert _link_name(a) == "px4-dds (domain 7, ns vehicle_2)"


@pytest.mark.netns
def test_dds_iface_keeps_link_and_px4_on_that_interface() -> None:
    """``--dds-iface``: the link's DDS and the stand-in's (separate processes in a private
    namespace) meet on the namespace's veth only, configured as the V2V over DDS is
    (``comms.dds.interface_config``), and the link drives the vehicle."""
    from openconvoy.comms.netns import IFACE, run_in_netns

    peer = str(HERE / "px4dds_iface_peer.py")
    veh, lo, lk = run_in_netns(
        [[sys.executable, peer, "vehicle", "12"], [sys.executable, peer, "link", "lo"]]
        + [[sys.executable, peer, "link", IFACE]],
        timeout=60,
        stagger_s=0.5,
    )
    for r in (veh, lo, lk):
        assert r.returncode == 0, r.stderr[-1500:]
    # A link kept on loopback does not find the vehicle kept on the veth.
    assert not json.loads(lo.stdout)["connected"]
    seen, moved = json.loads(lk.stdout.strip().splitlines()[-1]), json.loads(veh.stdout)
    assert seen["armed"] and seen["x"] > 1.0  # east, as the link reads it
    assert moved["x"] > 1.0  # and as the vehicle moved


def test_dds_localhost_and_iface_together_are_refused() -> None:
    with pytest.raises(ConfigError, match="--dds-localhost and --dds-iface: choose one"):
        Px4DdsLink("v", DEFAULT_HOME, 1, localhost=True, iface="oc0")
