"""MavlinkLink against the simulated vehicle, over real MAVLink bytes on localhost."""

from __future__ import annotations

import math
import socket
import time

import pytest

from openconvoy.bridge.link import CommandRefused, LinkLost, LinkTimeout, VehicleLink
from openconvoy.bridge.mavlink.link import MavlinkLink, check_url
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.testing import free_port, run_for, wait_for


def test_urls_are_checked() -> None:
    for url in (
        "udpin:0.0.0.0:14550",
        "udpout:10.0.0.2:14550",
        "udp:127.0.0.1:1",
        "tcp:192.168.1.5:5760",
        "tcpin:0.0.0.0:5760",
        "/dev/ttyUSB0",
    ):
        assert check_url(url) == url
    for bad in ("udp:14550", "tcp:host:port", "http://x", "serial0"):
        with pytest.raises(ValueError, match="MAVLink URL"):
            check_url(bad)


def test_no_heartbeat_times_out() -> None:
    link = MavlinkLink(f"udpout:127.0.0.1:{free_port()}", DEFAULT_HOME)
    t0 = time.monotonic()
    with pytest.raises(LinkTimeout, match="no heartbeat"):
        link.connect(timeout_s=0.5)
    assert time.monotonic() - t0 < 2.0
    link.close()


def test_a_long_wait_for_a_heartbeat_is_said_after_3_s() -> None:
    """Waiting longer than ~3 s for a vehicle is never silent: one status line, once."""
    said: list[str] = []
    link = MavlinkLink(f"udpout:127.0.0.1:{free_port()}", DEFAULT_HOME, on_status=said.append)
    t0 = time.monotonic()
    with pytest.raises(LinkTimeout, match="no heartbeat"):
        link.connect(timeout_s=3.5)
    assert 3.4 < time.monotonic() - t0 < 6.0
    assert len(said) == 1 and said[0].startswith("no heartbeat on udpout:127.0.0.1:")
    assert "waiting up to 0.5 s more for the vehicle" in said[0]
    link.close()


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_identify_and_telemetry_in_enu(vehicle_and_link, autopilot) -> None:
    # The convoy origin lies 100 m west and 50 m south of the vehicle's home, so the link's
    # ENU position is the vehicle's plus (100, 50): geodetic -> ENU around another origin.
    lat, lon, _ = enu_to_geodetic(DEFAULT_HOME, -100.0, -50.0)
    origin = Origin(lat, lon, 0.0)
    vehicle, link, _ = vehicle_and_link(
        autopilot=autopilot,
        system_id=7,
        start_x_m=3.0,
        start_y_m=-4.0,
        start_heading_rad=math.radians(30.0),
        link_kwargs=dict(origin=origin, vehicle_id=2, telemetry_hz=20.0, length_m=0.8),
    )
    assert isinstance(link, VehicleLink)
    assert link.autopilot == autopilot
    assert link.telemetry_rates == {"GLOBAL_POSITION_INT": 20.0, "ATTITUDE": 20.0}
    assert wait_for(lambda: link.inbox.telemetry is not None, 2.0, link)
    tel = link.inbox.telemetry
    assert tel.state.vehicle_id == 2 and tel.state.length == 0.8
    assert tel.state.x == pytest.approx(103.0, abs=0.05)
    assert tel.state.y == pytest.approx(46.0, abs=0.05)
    assert tel.state.heading == pytest.approx(math.radians(30.0), abs=1e-3)
    assert tel.state.speed == pytest.approx(0.0, abs=1e-6)
    assert abs(tel.state.t - time.time()) < 1.0  # wall clock
    assert tel.mode == ("MANUAL" if autopilot == "ardupilot" else "LOITER")  # INITIAL_MODE
    assert tel.armed is False
    assert link.link_ok(time.monotonic())


def test_refused_rate_is_reported_and_lowered(vehicle_and_link) -> None:
    vehicle, link, lines = vehicle_and_link(
        max_message_hz=30.0, link_kwargs=dict(telemetry_hz=50.0)
    )
    # 50 refused, 40 refused, 25 accepted — for both messages, each refusal reported.
    assert link.telemetry_rates == {"GLOBAL_POSITION_INT": 25.0, "ATTITUDE": 25.0}
    refused = [line for line in lines if "refused" in line]
    assert len(refused) == 4 and "50 Hz" in refused[0] and "40 Hz" in refused[1]
    assert vehicle.message_rates_hz["GLOBAL_POSITION_INT"] == pytest.approx(25.0)
    # The achieved rate at the link.
    run_for(link, 0.3)
    before = link.inbox.counts.get("GLOBAL_POSITION_INT", 0)
    t0 = time.monotonic()
    run_for(link, 2.0, period=0.01)
    rate = (link.inbox.counts["GLOBAL_POSITION_INT"] - before) / (time.monotonic() - t0)
    assert 20.0 <= rate <= 27.0


def test_arming_waits_for_the_estimator(vehicle_and_link) -> None:
    vehicle, link, _ = vehicle_and_link(ready_after_s=3.0)
    status: list[str] = []
    link.modes.prepare_and_arm(timeout_s=10.0, on_status=status.append)
    assert link.watch.armed and link.watch.mode == "GUIDED"
    assert vehicle.armed and vehicle.mode == "GUIDED"
    assert vehicle.state().t >= 3.0
    waiting = [s for s in status if s.startswith("waiting to arm")]
    assert waiting, status
    assert "MAV_RESULT_FAILED" in waiting[0]
    assert "AHRS: not using configured AHRS type" in waiting[0]


def test_arming_timeout_names_command_and_reason(vehicle_and_link) -> None:
    _, link, _ = vehicle_and_link(ready_after_s=100.0)
    with pytest.raises(CommandRefused) as err:
        link.modes.prepare_and_arm(timeout_s=2.0, on_status=lambda line: None)
    assert err.value.command == "MAV_CMD_COMPONENT_ARM_DISARM"
    assert err.value.result == "MAV_RESULT_FAILED"
    assert "AHRS" in err.value.reason
    assert "MAV_CMD_COMPONENT_ARM_DISARM" in str(err.value) and "AHRS" in str(err.value)


def test_guided_setpoints_drive_speed_and_heading(vehicle_and_link) -> None:
    vehicle, link, _ = vehicle_and_link(start_heading_rad=0.0)
    link.modes.prepare_and_arm(timeout_s=10.0)
    north = math.pi / 2
    run_for(link, 4.0, speed=1.5, heading=north)
    truth = vehicle.state()
    assert truth.speed == pytest.approx(1.5, abs=0.03)
    assert truth.heading == pytest.approx(north, abs=0.02)
    tel = link.inbox.telemetry
    assert tel.state.speed == pytest.approx(1.5, abs=0.05)
    assert tel.state.heading == pytest.approx(north, abs=0.03)
    assert tel.state.y > 2.0  # it went north
    # Stop: speed 0 along the current heading; the vehicle must not swing to another heading.
    end = time.monotonic() + 2.5
    while time.monotonic() < end:
        link.poll()
        link.setpoints.stop()
        time.sleep(0.05)
    truth = vehicle.state()
    assert abs(truth.speed) < 0.02
    assert truth.heading == pytest.approx(north, abs=0.03)
    # A requested HOLD is not a pilot takeover.
    link.modes.hold(timeout_s=3.0)
    assert vehicle.mode == "HOLD" and not link.modes.pilot_took_over


def test_setpoint_timeout_stops_the_rover_after_3_s(vehicle_and_link) -> None:
    vehicle, link, _ = vehicle_and_link()
    assert vehicle.config.setpoint_timeout_s == 3.0  # the default, as ArduPilot
    link.modes.prepare_and_arm(timeout_s=10.0)
    run_for(link, 2.0, speed=1.0, heading=0.0)
    assert vehicle.state().speed == pytest.approx(1.0, abs=0.05)
    t_last = time.monotonic()
    run_for(link, 2.5)  # no setpoints: still going
    assert vehicle.state().speed == pytest.approx(1.0, abs=0.05)
    assert wait_for(lambda: abs(vehicle.state().speed) < 0.01, 4.0, link)
    stopped_after = time.monotonic() - t_last
    assert 3.0 <= stopped_after <= 5.5  # 3 s timeout + ~1 s braking at 1 m/s²
    assert vehicle.mode == "GUIDED" and link.watch.mode == "GUIDED"  # ArduPilot stays in GUIDED
    assert not link.modes.pilot_took_over


def test_pilot_takeover_is_latched(vehicle_and_link) -> None:
    vehicle, link, lines = vehicle_and_link()
    link.modes.prepare_and_arm(timeout_s=10.0)
    run_for(link, 1.0, speed=1.0, heading=0.0)
    assert not link.modes.pilot_took_over
    vehicle.pilot_set_mode("MANUAL")
    assert wait_for(lambda: link.modes.pilot_took_over, 2.5, link)
    assert link.watch.mode == "MANUAL"
    assert link.setpoints.send(1.0, 0.0) is False
    assert link.setpoints.stop() is False
    assert any("took over" in line for line in lines)
    with pytest.raises(CommandRefused):
        link.modes.prepare_and_arm(timeout_s=1.0)


def test_px4_offboard_needs_the_stream_and_leaves_without_it(vehicle_and_link) -> None:
    vehicle, link, _ = vehicle_and_link(autopilot="px4")
    link.modes.set_mode("OFFBOARD", timeout_s=2.0)  # real PX4 accepts it disarmed without a stream
    assert vehicle.mode == "OFFBOARD"  # (shared/sitl-px4 row 3); arming there needs the stream

    t0 = time.monotonic()
    link.modes.prepare_and_arm(timeout_s=10.0)  # streams 1.2 s first, then OFFBOARD, then arms
    assert time.monotonic() - t0 >= 1.2
    assert vehicle.mode == "OFFBOARD" and vehicle.armed
    run_for(link, 3.5, speed=1.0, heading=-math.pi / 2)
    truth = vehicle.state()
    assert truth.speed == pytest.approx(1.0, abs=0.05)
    assert truth.heading == pytest.approx(-math.pi / 2, abs=0.03)

    # The stream stops: COM_OF_LOSS_T (1 s) without a setpoint -> failsafe, POSCTL, braking.
    t_last = time.monotonic()
    assert wait_for(lambda: vehicle.mode == "POSCTL", 3.0, link)
    left_after = time.monotonic() - t_last
    assert 0.9 <= left_after <= 1.6
    assert wait_for(lambda: link.modes.pilot_took_over, 2.0, link)  # not our request
    assert wait_for(lambda: abs(vehicle.state().speed) < 0.01, 3.0, link)


def test_frozen_vehicle_makes_the_link_not_ok(vehicle_and_link) -> None:
    vehicle, link, _ = vehicle_and_link()
    run_for(link, 0.3)
    assert link.link_ok(time.monotonic())
    vehicle.freeze()
    run_for(link, 0.7)
    assert not link.link_ok(time.monotonic())
    vehicle.freeze(False)
    assert wait_for(lambda: link.link_ok(time.monotonic()), 2.0, link)


def test_tcp_eof_is_a_lost_link_and_reconnect_works() -> None:
    port = free_port(socket.SOCK_STREAM)
    config = SimVehicleConfig(ready_after_s=0.0)
    vehicle = SimVehicle(f"tcpin:127.0.0.1:{port}", config).start()
    link = MavlinkLink(f"tcp:127.0.0.1:{port}", DEFAULT_HOME, on_status=lambda line: None)
    try:
        link.connect(timeout_s=5.0)
        run_for(link, 0.3)
        assert link.link_ok(time.monotonic()) and not link.lost
        vehicle.stop()  # killed: the socket closes, pymavlink sees EOF
        assert wait_for(lambda: link.lost, 1.0, link)
        assert not link.link_ok(time.monotonic())
        t0 = time.monotonic()
        for _ in range(200):
            assert link.poll() is None
        assert time.monotonic() - t0 < 0.2  # no busy loop inside poll
        with pytest.raises(LinkLost):  # nobody listening: refused at once
            link.reconnect(timeout_s=0.2)
        assert link.lost
        vehicle = SimVehicle(f"tcpin:127.0.0.1:{port}", config).start()
        # The runner's way: short attempts every tick until a heartbeat arrives.
        end = time.monotonic() + 5.0
        while True:
            try:
                link.reconnect(timeout_s=0.2)
                break
            except LinkTimeout:
                assert time.monotonic() < end
        run_for(link, 0.3)
        assert link.link_ok(time.monotonic()) and not link.lost
        assert vehicle.message_rates_hz["GLOBAL_POSITION_INT"] == pytest.approx(20.0)
    finally:
        link.close()
        vehicle.stop()


def test_restarted_udp_vehicle_gets_its_telemetry_rates_again(vehicle_and_link) -> None:
    vehicle, link, lines = vehicle_and_link(link_kwargs=dict(telemetry_hz=20.0))
    run_for(link, 1.5)
    assert link.link_ok(time.monotonic())
    url, config = vehicle.url, vehicle.config
    vehicle.stop()  # a reboot: the new autopilot starts at its default rates
    run_for(link, 0.6)
    assert not link.link_ok(time.monotonic())
    vehicle = SimVehicle(url, config).start()
    try:
        assert vehicle.message_rates_hz["GLOBAL_POSITION_INT"] == pytest.approx(1.0)
        # No reconnect needed on UDP: poll notices the vehicle is back and asks again.
        assert wait_for(lambda: vehicle.message_rates_hz["GLOBAL_POSITION_INT"] == 20.0, 5.0, link)
        assert wait_for(lambda: link.link_ok(time.monotonic()), 1.0, link)
        assert any("requesting telemetry again" in line for line in lines)
    finally:
        vehicle.stop()


def test_link_listens_for_a_vehicle_that_sends_first() -> None:
    """The other common wiring: the autopilot (or a radio) sends to the companion's port."""
    port = free_port()
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", DEFAULT_HOME, on_status=lambda line: None)
    vehicle = SimVehicle(f"udpout:127.0.0.1:{port}", SimVehicleConfig(ready_after_s=0.0))
    try:
        vehicle.start()
        link.connect(timeout_s=5.0)
        assert link.autopilot == "ardupilot" and link.telemetry_rates["ATTITUDE"] == 20.0
        link.modes.prepare_and_arm(timeout_s=10.0)
        assert vehicle.armed and vehicle.mode == "GUIDED"
    finally:
        link.close()
        vehicle.stop()


FLT_EPSILON = 1.1920929e-07


def test_every_quadrant_drives_forward_and_the_old_encoding_reverses_where_the_firmware_did(
    vehicle_and_link,
) -> None:
    """Against the simulated ArduPilot, over MAVLink: MavlinkLink's setpoints drive forward
    at headings in all four quadrants; the old encoding (NED (vx, vy) with yaw, e9a5f3e)
    reverses exactly where real Rover 4.7 did (shared/sitl row 7: vx <= -FLT_EPSILON)."""
    vehicle, link, _ = vehicle_and_link(start_heading_rad=0.0)
    link.modes.prepare_and_arm(timeout_s=10.0)
    ts, tc = link.watch.target

    def drive(send, seconds: float = 1.5) -> float:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            link.poll()
            send()
            time.sleep(0.05)
        return vehicle.state().speed

    for compass in (45.0, 135.0, 225.0, 315.0):
        heading = math.radians(90.0 - compass)
        assert drive(lambda h=heading: link.setpoints.send(1.0, h)) > 0.3, compass
        drive(link.setpoints.stop, 1.2)
    for compass in (45.0, 135.0, 225.0, 315.0):
        yaw = math.radians(compass)
        vn, ve = math.cos(yaw), math.sin(yaw)

        def old(vn=vn, ve=ve, yaw=yaw) -> None:
            link._link.conn.mav.set_position_target_global_int_send(
                0, ts, tc, 6, 2503, 0, 0, 0.0, vn, ve, 0.0, 0.0, 0.0, 0.0, yaw, 0.0
            )

        speed = drive(old)
        assert (speed < -0.3) if vn <= -FLT_EPSILON else (speed > 0.3), (compass, speed)
        drive(link.setpoints.stop, 1.2)


@pytest.mark.parametrize(
    ("autopilot", "reasons"),
    [
        # PX4's refusal is longer than one STATUSTEXT: it comes in two chunks (shared/sitl-px4).
        ("px4", ["Arming denied: Resolve system health failures first"]),
        # ArduPilot in GUIDED early in boot fails two checks and sends a text for each.
        ("ardupilot", ["Arm: Accels inconsistent", "Arm: AHRS: not using configured AHRS type"]),
    ],
)
def test_an_arming_refusal_names_the_autopilots_whole_reasons(
    vehicle_and_link, autopilot: str, reasons: list[str]
) -> None:
    _, link, _ = vehicle_and_link(autopilot=autopilot, ready_after_s=100.0)
    with pytest.raises(CommandRefused) as err:
        link.modes.prepare_and_arm(timeout_s=2.5, on_status=lambda line: None)
    assert err.value.reason == "; ".join(reasons)
