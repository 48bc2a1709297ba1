"""The simulated vehicle's AUTOPILOTS.md behaviours, probed with raw pymavlink messages."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import pytest

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.envs.vehicles import VEHICLE_PRESETS
from openconvoy.testing import free_port

ACCEL_IN_USE = mp.TYPE_MASK_VEL_YAW & ~mp.MASK_ACC


class Gcs:
    """A bare pymavlink peer: what any ground station or companion would send."""

    def __init__(self, port: int, sysid: int = 1) -> None:
        self.conn = mp.mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=250, source_component=190
        )
        self.sysid = sysid
        self.heartbeat: Any = None

    def hello(self, timeout: float = 5.0) -> Any:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.conn.mav.heartbeat_send(mp.MAV_TYPE_GCS, 8, 0, 0, 4)
            msg = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
            if msg is not None:
                self.heartbeat = msg
                return msg
        raise AssertionError("no heartbeat from the simulated vehicle")

    def command(self, cmd: int, *params: float) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(self.sysid, 1, cmd, 0, *p)
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            msg = self.conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
            if msg is not None and msg.command == cmd:
                return msg.result
        raise AssertionError(f"no COMMAND_ACK for {cmd}")

    def next_heartbeat(self) -> Any:
        msg = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0)
        assert msg is not None
        return msg

    def velocity(self, vn: float, ve: float, yaw: float, mask: int, local: bool = False) -> None:
        if local:
            self.conn.mav.set_position_target_local_ned_send(
                0, self.sysid, 1, mp.MAV_FRAME_LOCAL_NED, mask, 0, 0, 0, vn, ve, 0, 0, 0, 0, yaw, 0
            )
        else:
            self.conn.mav.set_position_target_global_int_send(
                0,
                self.sysid,
                1,
                mp.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                mask,
                0,
                0,
                0,
                vn,
                ve,
                0,
                0,
                0,
                0,
                yaw,
                0,
            )

    def stream(
        self, seconds: float, vn: float, ve: float, yaw: float, mask: int, local: bool = False
    ) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.velocity(vn, ve, yaw, mask, local)
            self.conn.recv_msg()  # keep the socket drained
            time.sleep(0.05)

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def sim() -> Iterator[Any]:
    made: list[tuple[SimVehicle, Gcs]] = []

    def make(**config: Any) -> tuple[SimVehicle, Gcs]:
        port = free_port()
        vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", SimVehicleConfig(**config)).start()
        gcs = Gcs(port)
        made.append((vehicle, gcs))
        gcs.hello()
        return vehicle, gcs

    yield make
    for vehicle, gcs in made:
        gcs.close()
        vehicle.stop()


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_heartbeat_identifies_the_autopilot(sim, autopilot) -> None:
    vehicle, gcs = sim(autopilot=autopilot, ready_after_s=0.0)
    hb = gcs.next_heartbeat()
    assert hb.type == 10  # MAV_TYPE_GROUND_ROVER
    assert hb.autopilot == (3 if autopilot == "ardupilot" else 12)
    assert not hb.base_mode & 128
    if autopilot == "ardupilot":
        assert hb.custom_mode == 0  # MANUAL: INITIAL_MODE after boot
    else:
        assert hb.custom_mode == (4 << 16 | 3 << 24)  # AUTO.LOITER


def test_ardupilot_setpoint_rules(sim) -> None:
    vehicle, gcs = sim(
        ready_after_s=0.0, ekf_origin_after_s=2.5, wp_speed_mps=1.0, preset=VEHICLE_PRESETS["1/10"]
    )
    east = math.pi / 2  # NED yaw of east
    assert gcs.command(mp.CMD_COMPONENT_ARM_DISARM, 1) == mp.RESULT_ACCEPTED
    # Outside GUIDED (MANUAL): ignored.
    gcs.stream(0.3, 0.0, 1.0, east, mp.TYPE_MASK_VEL_YAW)
    assert vehicle.setpoints_received == 0 and vehicle.setpoints_ignored > 0
    assert gcs.command(mp.CMD_DO_SET_MODE, 1, 15) == mp.RESULT_ACCEPTED
    # LOCAL_NED before the EKF has an origin: ignored.
    ignored = vehicle.setpoints_ignored
    gcs.stream(0.3, 0.0, 1.0, east, mp.TYPE_MASK_VEL_YAW, local=True)
    assert vehicle.setpoints_received == 0 and vehicle.setpoints_ignored > ignored
    # Acceleration bits not all "ignore": dropped, also in GLOBAL_INT.
    ignored = vehicle.setpoints_ignored
    gcs.stream(0.3, 0.0, 1.0, east, ACCEL_IN_USE)
    assert vehicle.setpoints_received == 0 and vehicle.setpoints_ignored > ignored
    assert abs(vehicle.state().speed) < 1e-6
    # A proper GLOBAL_INT setpoint at 3 m/s: accepted, speed capped by WP_SPEED (1 m/s).
    gcs.stream(2.0, 0.0, 3.0, east, mp.TYPE_MASK_VEL_YAW)
    assert vehicle.setpoints_received > 0
    assert vehicle.state().speed == pytest.approx(1.0, abs=0.02)
    # After the EKF origin, LOCAL_NED works too.
    while vehicle.state().t < 2.6:
        time.sleep(0.05)
    received = vehicle.setpoints_received
    gcs.stream(0.3, 0.0, 1.0, east, mp.TYPE_MASK_VEL_YAW, local=True)
    assert vehicle.setpoints_received > received


def test_zero_velocity_only_setpoint_steers_to_north(sim) -> None:
    """AUTOPILOTS.md's gotcha, reproduced: "stop" as a zero velocity vector means heading
    north with speed 0, so a rover still rolling turns towards north."""
    vehicle, gcs = sim(ready_after_s=0.0)
    assert gcs.command(mp.CMD_COMPONENT_ARM_DISARM, 1) == mp.RESULT_ACCEPTED
    assert gcs.command(mp.CMD_DO_SET_MODE, 1, 15) == mp.RESULT_ACCEPTED
    gcs.stream(2.0, 0.0, 1.0, math.pi / 2, mp.TYPE_MASK_VEL_YAW)  # east at 1 m/s
    assert vehicle.state().heading == pytest.approx(0.0, abs=0.02)
    gcs.stream(2.5, 0.0, 0.0, 0.0, mp.TYPE_MASK_VEL)
    state = vehicle.state()
    assert abs(state.speed) < 0.05  # nearly stopped
    assert state.heading > 0.2  # turned left, towards north (ENU pi/2), while braking


def test_message_intervals(sim) -> None:
    vehicle, gcs = sim()
    assert gcs.command(mp.CMD_SET_MESSAGE_INTERVAL, mp.MSG_ATTITUDE, 1e6 / 40) == mp.RESULT_ACCEPTED
    assert gcs.command(mp.CMD_SET_MESSAGE_INTERVAL, mp.MSG_ATTITUDE, 1e6 / 50) == mp.RESULT_DENIED
    assert vehicle.message_rates_hz["ATTITUDE"] == pytest.approx(40.0)
    assert gcs.command(mp.CMD_SET_MESSAGE_INTERVAL, mp.MSG_VFR_HUD, -1) == mp.RESULT_ACCEPTED
    assert vehicle.message_rates_hz["VFR_HUD"] == 0.0
    assert gcs.command(mp.CMD_SET_MESSAGE_INTERVAL, mp.MSG_ATTITUDE, 0) == mp.RESULT_ACCEPTED
    assert vehicle.message_rates_hz["ATTITUDE"] == pytest.approx(1.0)
    assert gcs.command(mp.CMD_SET_MESSAGE_INTERVAL, 9999, 1e5) == mp.RESULT_FAILED
    assert gcs.command(31000, 0) == mp.RESULT_UNSUPPORTED  # an unknown command


def test_px4_arming_in_offboard_needs_the_stream(sim) -> None:
    vehicle, gcs = sim(autopilot="px4", ready_after_s=0.0)
    assert gcs.command(mp.CMD_DO_SET_MODE, 1, 6, 0) == mp.RESULT_ACCEPTED  # disarmed: allowed
    assert gcs.command(mp.CMD_COMPONENT_ARM_DISARM, 1) == mp.RESULT_TEMPORARILY_REJECTED
    gcs.stream(0.4, 0.0, 0.0, 0.0, mp.TYPE_MASK_VEL_YAW, local=True)
    assert gcs.command(mp.CMD_COMPONENT_ARM_DISARM, 1) == mp.RESULT_ACCEPTED
    assert vehicle.armed


def _px4_driving_east(bias_deg: float, seconds: float = 10.0):
    """The simulated PX4 (its firmware model on SIH's rover physics), armed in OFFBOARD,
    streaming 1.5 m/s east (LOCAL_NED 3527) at 20 Hz from rest facing east."""
    from openconvoy.bridge.mavlink import protocol as mp
    from openconvoy.bridge.simvehicle.motion import MotionState
    from openconvoy.bridge.simvehicle.px4 import LOOP_DT, Px4Rover, Px4Timing

    state = MotionState(yaw=math.pi / 2, yaw_bias=math.radians(bias_deg))
    fw = Px4Rover(state, Px4Timing.short(0.0), 28.6024, -81.2001)
    t = 0.0
    track = []
    for k in range(int(seconds / LOOP_DT)):
        if k % 2 == 0:  # 25 Hz
            fw.setpoint(t, True, 1, 3527, 0.0, 1.5, 0.0, 0.0)
        if k == 10:
            assert fw.command(t, mp.CMD_DO_SET_MODE, [1.0, 6.0, 0.0]) == mp.RESULT_ACCEPTED
            assert fw.command(t, mp.CMD_COMPONENT_ARM_DISARM, [1.0]) == mp.RESULT_ACCEPTED
        fw.tick(t)
        track.append((t, state.north, state.east))
        t += LOOP_DT
    return state, track


def test_px4_ekf_heading_bias_steers_the_rover_off_its_bearing() -> None:
    """PX4 holds its EKF yaw on the bearing (shared/sitl-px4/README.md §4: EKF - true
    +0.7..+5.8°, the rover really drives that far off): with a +5° bias the estimate
    settles on east and the true yaw and course 5° short of it."""
    state, track = _px4_driving_east(5.0)
    assert math.degrees(state.estimated_yaw) == pytest.approx(90.0, abs=0.5)
    assert math.degrees(state.yaw) == pytest.approx(85.0, abs=0.5)
    (_, n0, e0), (_, n1, e1) = track[-101], track[-1]
    course = math.degrees(math.atan2(e1 - e0, n1 - n0))
    assert course == pytest.approx(85.0, abs=1.0)
    unbiased, _ = _px4_driving_east(0.0)
    assert math.degrees(unbiased.yaw) == pytest.approx(90.0, abs=0.5)


def test_px4_heading_bias_is_drawn_per_vehicle_and_run() -> None:
    from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig

    def bias(seed: int, autopilot: str = "px4") -> float:
        cfg = SimVehicleConfig(autopilot=autopilot, heading_bias_max_deg=8.0, seed=seed)
        return math.degrees(SimVehicle("udpin:127.0.0.1:0", cfg).motion_state.yaw_bias)

    drawn = [bias(s) for s in range(40)]
    assert all(abs(b) <= 8.0 for b in drawn) and len(set(drawn)) == 40
    assert bias(3) == bias(3)  # the same run again
    assert min(drawn) < -4.0 and max(drawn) > 4.0
    assert bias(3, "ardupilot") == 0.0
    with pytest.raises(ValueError, match="heading_bias_max_deg"):
        SimVehicleConfig(autopilot="px4", heading_bias_max_deg=90.0)


def test_px4_clock_ratio_is_configurable() -> None:
    """SIH's clock runs at 0.990 of real time (sitl-px4 row 24); the demo's PX4s use it."""
    from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig

    def ratio(**kw: Any) -> float:
        cfg = SimVehicleConfig(autopilot="px4", **kw)
        return SimVehicle("udpin:127.0.0.1:0", cfg).firmware.clock_ratio

    assert ratio() == 1.0 and ratio(timing="firmware") == 0.990
    assert ratio(px4_clock_ratio=0.990) == 0.990
    with pytest.raises(ValueError, match="px4_clock_ratio"):
        SimVehicleConfig(autopilot="px4", px4_clock_ratio=0.1)
