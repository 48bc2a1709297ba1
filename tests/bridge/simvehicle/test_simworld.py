"""The simulated vehicle's forward rangefinder: DISTANCE_SENSOR from a ``SimWorld``, over
real MAVLink bytes on localhost, read raw and by ``MavlinkLink``."""

from __future__ import annotations

import dataclasses
import math
import time

import pytest

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.simvehicle.streams import RANGE_HZ
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.bridge.simvehicle.world import SimWorld, distance_sensor_cm
from openconvoy.envs.vehicles import VEHICLE_PRESETS, RangingSensor
from openconvoy.testing import free_port, wait_for

P = VEHICLE_PRESETS["1/10"]
EXACT = P.with_ranging(RangingSensor(max_range_m=20.0, range_noise_m=0.0))


def _pair(world: SimWorld, gap_m: float, ahead_heading: float = 0.0, **ego):
    """An ego at the origin facing east with a rangefinder, and a vehicle whose rear
    bumper is ``gap_m`` ahead of the ego's front bumper (not running: it just stands there)."""
    port = free_port()
    ego_v = SimVehicle(
        f"udpin:127.0.0.1:{port}",
        SimVehicleConfig(
            system_id=2,
            preset=EXACT,
            ready_after_s=0.0,
            init_s=0.0,
            rc_mode_switch=False,
            **ego,
        ),
        world=world,
    )
    ahead = SimVehicle(
        f"udpin:127.0.0.1:{free_port()}",
        SimVehicleConfig(
            system_id=1,
            preset=P,
            start_x_m=gap_m + P.length_m,
            start_heading_rad=ahead_heading,
        ),
        world=world,
    )
    return ego_v.start(), ahead, port


def test_bumper_geometry_field_of_view_and_nearest() -> None:
    world = SimWorld()
    ego, ahead, _ = _pair(world, 10.0)
    ego.stop()
    assert world.forward_range(2, 20.0) == pytest.approx((10.0, 0.0), abs=1e-9)
    assert world.forward_range(2, 9.9) is None  # beyond the sensor's range
    assert world.forward_range(1, 20.0) is None  # the one ahead sees nothing (ego is behind)
    # A closer vehicle 5 m ahead but 3 m to the side is outside the ±15° cone; 0.5 m aside, inside.
    x = 5.0 + P.length_m
    world.register(3, lambda: dataclasses.replace(ahead.state(), x=x, y=3.0), P.length_m)
    assert world.forward_range(2, 20.0)[0] == pytest.approx(10.0)
    world.register(3, lambda: dataclasses.replace(ahead.state(), x=x, y=0.5), P.length_m)
    assert world.forward_range(2, 20.0)[0] == pytest.approx(math.hypot(x, 0.5) - P.length_m)


def test_no_target_reads_max_plus_one_metre_as_ardupilot_lidars() -> None:
    assert distance_sensor_cm(None, 20.0, 0.0, lambda: 0.0) == (1, 2000, 2100)
    assert distance_sensor_cm((12.345, 0.0), 20.0, 0.0, lambda: 0.0) == (1, 2000, 1234)
    assert distance_sensor_cm((12.0, 0.0), 20.0, 0.1, lambda: 2.0) == (1, 2000, 1220)


def test_distance_sensor_on_the_wire_at_its_rate() -> None:
    world = SimWorld()
    ego, ahead, port = _pair(world, 10.0)
    conn = mp.mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255)
    try:
        conn.mav.heartbeat_send(6, 8, 0, 0, 0)
        msgs = []
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            m = conn.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=0.2)
            if m is not None:
                msgs.append(m)
        assert len(msgs) >= 20
        m = msgs[-1]
        assert (m.min_distance, m.max_distance, m.current_distance) == (1, 2000, 1000)
        assert (m.orientation, m.type) == (0, 0)  # MAV_SENSOR_ROTATION_NONE, laser
        dt = (msgs[-1].time_boot_ms - msgs[1].time_boot_ms) / 1000 / (len(msgs) - 2)
        assert dt == pytest.approx(1.0 / RANGE_HZ, rel=0.05)
        world.unregister(1)  # the vehicle ahead is gone
        time.sleep(0.2)
        m = conn.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=1.0)
        while (n := conn.recv_match(type="DISTANCE_SENSOR", blocking=False)) is not None:
            m = n
        assert m.current_distance == 2100
    finally:
        conn.close()
        ego.stop()


def test_no_world_no_rangefinder() -> None:
    port = free_port()
    v = SimVehicle(
        f"udpin:127.0.0.1:{port}", SimVehicleConfig(preset=EXACT, ready_after_s=0.0)
    ).start()
    try:
        assert "DISTANCE_SENSOR" not in v.message_rates_hz
    finally:
        v.stop()


def test_mavlink_link_reads_the_range_and_loses_it_when_nothing_is_ahead() -> None:
    world = SimWorld()
    ego, ahead, port = _pair(world, 10.0)
    link = MavlinkLink(
        f"udpout:127.0.0.1:{port}", DEFAULT_HOME, vehicle_id=1, on_status=lambda line: None
    )
    try:
        link.connect(timeout_s=5.0)

        def tel():
            return link.inbox.telemetry

        assert wait_for(
            lambda: tel() is not None and math.isfinite(tel().range_rate_mps), 3.0, link
        )
        t = tel()
        assert t.range_m == pytest.approx(10.0, abs=0.005)
        assert t.range_rate_mps == pytest.approx(0.0, abs=1e-6)
        world.unregister(1)
        assert wait_for(lambda: math.isnan(tel().range_m), 2.0, link)
        assert math.isnan(tel().range_rate_mps)
    finally:
        link.close()
        ego.stop()
