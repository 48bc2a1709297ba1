"""tests/data/sitl-px4/README.md's conformance table: recordings of real PX4 (SIH rover)
replayed into the simulated PX4 vehicle; the same measurement on both sides. Headings
come from the EKF's ATTITUDE, speeds from SIH's true state (HIL_STATE_QUATERNION on the
simulator link) for the firmware and from the simulated vehicle's true GLOBAL_POSITION_INT."""

from __future__ import annotations

import math

import pytest
from conformance import (
    acks,
    angle_diff,
    circular_mean,
    heartbeats,
    mean,
    motion,
    phase,
    rx,
    sides,
    texts,
    yaw_series,
)

SIDES = ("firmware", "sim")
DENIED = "Arming denied: Resolve system health failures first"
OFFBOARD = 6 << 16
POSCTL = 3 << 16
LOITER = 4 << 16 | 3 << 24


def run(name: str) -> dict:
    return sides("sitl-px4", name)


def truth(side: str, recs: list, t0: float, t1: float) -> list[tuple[float, float, float]]:
    """(t, speed m/s, forward speed m/s): SIH's true state for the firmware, the simulated
    vehicle's (true) GLOBAL_POSITION_INT for the simulation."""
    if side == "sim":
        return [(t, abs(v), v) for t, v, _, _ in motion(recs, t0, t1)]
    out = []
    for r in rx(recs, "HIL_STATE_QUATERNION", t0, t1, link="sih"):
        f = r["fields"]
        w, x, y, z = f["attitude_quaternion"]
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        vn, ve = f["vx"] / 100.0, f["vy"] / 100.0
        out.append((r["t"], math.hypot(vn, ve), vn * math.cos(yaw) + ve * math.sin(yaw)))
    return out


def settle(samples: list[tuple[float, float, float]], t0: float) -> tuple[float, float]:
    """(final speed: mean of the last 2 s, time after t0 from which it stays within 0.05)."""
    t_end = samples[-1][0]
    final = mean([v for t, v, _ in samples if t >= t_end - 2.0])
    last_out = max((t for t, v, _ in samples if abs(v - final) > 0.05), default=t0)
    return final, last_out - t0


def test_row_01_boots_in_hold_as_a_px4_rover() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        first = rx(recs, "HEARTBEAT")[0]
        assert 1.3 <= first["t"] - run("boot_and_arm")["boot"] <= 1.95, side
        f = first["fields"]
        assert (f["type"], f["autopilot"], f["custom_mode"]) == (10, 12, LOITER), side


def test_row_02_arming_refused_until_healthy_then_accepted_in_hold() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        t_hb = rx(recs, "HEARTBEAT")[0]["t"]
        t0, t1, _ = phase(recs, "A_arm_in_hold")
        results = acks(recs, 400, t0, t1)
        accepted = next(t for t, r in results if r == 0)
        assert all(r == 1 for t, r in results if t < accepted), side
        assert 1.5 <= accepted - t_hb <= 5.0, (side, accepted - t_hb)
        assert any(s.startswith(DENIED) for _, s in texts(recs, t0, accepted + 0.5)), side


def test_rows_03_04_offboard_without_setpoints_accepted_disarmed_but_not_armable() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        t0, t1, _ = phase(recs, "B_offboard_no_setpoints")
        assert [r for _, r in acks(recs, 176, t0, t1)] == [0], side
        beats = [(m, b, s) for _, m, b, s in heartbeats(recs, t0 + 0.5, t1)]
        assert beats and all(b == (OFFBOARD, 1, 0) for b in beats), (side, beats)
        t0, t1, _ = phase(recs, "B2_arm_in_offboard_no_setpoints")
        assert [r for _, r in acks(recs, 400, t0, t1)] == [1, 1, 1], side
        assert sum(s.startswith(DENIED) for _, s in texts(recs, t0, t1)) == 3, side


def test_row_05_a_short_stream_admits_offboard_and_arming() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        t0, _, _ = phase(recs, "F2_stream_0.3s")
        _, t1, _ = phase(recs, "F3_arm")
        assert [r for _, r in acks(recs, 176, t0, t1)] == [0], side
        assert [r for _, r in acks(recs, 400, t0, t1)] == [0], side
        assert any(
            b & 128 and m == OFFBOARD and b == 145 for _, m, b, _ in heartbeats(recs, t0, t1)
        ), side


def test_row_06_offboard_while_armed_needs_the_stream() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        t0, t1, _ = phase(recs, "E2_offboard_armed_no_setpoints")
        assert [r for _, r in acks(recs, 176, t0, t1)] == [1], side
        assert any(
            s.startswith("Switching to Offboard is currently not available")
            for _, s in texts(recs, t0, t1)
        ), side


@pytest.mark.parametrize("case", ["L3527", "L2503yaw+90", "G6_3527", "G6_2503yaw+90"])
@pytest.mark.parametrize("direction", [0, 45, 90, 135, 180, 225, 270, 315])
def test_row_07_velocity_sets_the_bearing_and_the_yaw_field_is_ignored(
    case: str, direction: int
) -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        t0, t1, _ = phase(recs, f"{case}_dir{direction:03d}")
        yaw = circular_mean([y for _, y, _ in yaw_series(recs, t1 - 1.0, t1)])
        assert abs(angle_diff(yaw, direction)) <= 1.5, (side, yaw)


def test_row_10_local_offset_ned_is_rejected_with_a_text() -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        said = [s for _, s in texts(recs) if "coordinate frame 7 unsupported" in s]
        assert said and said[0].startswith(
            "SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported"
        ), side


@pytest.mark.parametrize("name", ["L1_silence", "L2_silence"])
def test_rows_16_17_offboard_loss_failsafe_and_return(name: str) -> None:
    fw = run("setpoint_loss")["firmware"]
    t0, t1, _ = phase(fw, name)
    last = max(
        r["t"]
        for r in fw
        if r["dir"] == "tx" and r["type"].startswith("SET_POSITION") and r["t"] < t0 + 0.01
    )
    for side in SIDES:
        recs = run("setpoint_loss")[side]
        fs = next(t for t, s in texts(recs, t0 - 0.2, t1) if s.startswith("Failsafe activated"))
        assert 1.0 <= fs - last <= 1.15, (side, fs - last)
        beats = heartbeats(recs, fs + 0.8, t1)
        assert all(m == POSCTL and b & 128 and s == 5 for _, m, b, s in beats), (side, beats)
        ys = [y for _, y, _ in yaw_series(recs, last, t1)]
        assert max(abs(angle_diff(y, ys[0])) for y in ys) < 2.0, side  # a straight brake
        resume = {"L1_silence": "L1_resume_2", "L2_silence": "L2_resume_1"}[name]
        r0, _, _ = phase(recs, resume)  # setpoints again, no mode command
        assert any(m == OFFBOARD for _, m, _, _ in heartbeats(recs, r0, r0 + 1.5)), side


@pytest.mark.parametrize(
    "name,toward",
    [
        ("S9_project_stop_yaw90.5", "south"),
        ("S10_project_stop_yaw89.5", "north"),
        ("S2_zero_2503_yaw90", "north"),
    ],
)
def test_rows_20_21_signed_zero_stops_swing(name: str, toward: str) -> None:
    for side in SIDES:
        recs = run("stops")[side]
        t0, t1, _ = phase(recs, name)
        ys = yaw_series(recs, t0 - 0.3, t1)
        start = [y for t, y, _ in ys if t < t0][-1]
        end = ys[-1][1]
        swing = angle_diff(end, start)
        assert abs(swing) > 30.0, (side, swing)
        assert (swing > 0) == (toward == "south"), (side, swing)


def test_row_22_zero_vector_at_rest_does_nothing() -> None:
    for side in SIDES:
        recs = run("stops")[side]
        t0, t1, _ = phase(recs, "S4_zero_at_rest")
        ys = [y for _, y, _ in yaw_series(recs, t0, t1)]
        assert max(abs(angle_diff(y, ys[0])) for y in ys) < 2.0, side


def test_row_24_the_sih_clock_runs_slow() -> None:
    for side in SIDES:
        recs = run("setpoint_loss")[side]
        att = rx(recs, "ATTITUDE", 20.0)
        a, b = att[0], att[-1]
        ratio = (
            (b["fields"]["time_boot_ms"] - a["fields"]["time_boot_ms"]) / 1000.0 / (b["t"] - a["t"])
        )
        assert abs(ratio - 0.990) <= 0.003, (side, ratio)


def test_row_08_velocity_behind_the_nose_is_a_forward_u_turn() -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        t0, t1, f = phase(recs, "R1_L2503_vx-1.5_yaw_current")
        bearing = math.degrees(math.atan2(f["vy"], f["vx"]))
        w5 = next(t for t, y, _ in yaw_series(recs, t0, t1) if abs(angle_diff(y, bearing)) <= 5.0)
        assert 1.5 <= w5 - t0 <= 3.5, (side, w5 - t0)
        assert min(fwd for _, _, fwd in truth(side, recs, t0, t1)) >= -0.05, side


def test_row_09_body_ned_backwards_circles() -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        t0, t1, _ = phase(recs, "R2_BODY_vx-1.5")
        rate = mean([abs(r) for _, _, r in yaw_series(recs, t0 + 1.5, t1)])
        assert rate > 60.0, (side, rate)
        assert min(fwd for _, _, fwd in truth(side, recs, t0, t1)) >= -0.05, side


def test_row_11_half_a_metre_per_second_does_not_start_it() -> None:
    for side in SIDES:
        recs = run("speed_steps")[side]
        t0, t1, _ = phase(recs, "low_v0.5")
        assert max(v for _, v, _ in truth(side, recs, t0, t1)) < 0.05, side


@pytest.mark.parametrize(
    "name", ["A1_v1.0", "A2_v2.0", "A3_v1.0", "paper1_v1.0", "paper2_v2.0", "cap_v3.0"]
)
def test_row_12_speed_steps_east(name: str) -> None:
    got = {}
    for side in SIDES:
        recs = run("speed_steps")[side]
        t0, t1, _ = phase(recs, name)
        got[side] = settle(truth(side, recs, t0, t1), t0)
    assert abs(got["sim"][0] - got["firmware"][0]) <= 0.05, got
    assert abs(got["sim"][1] - got["firmware"][1]) <= 0.3, got


@pytest.mark.parametrize("direction", [0, 45, 90])
def test_row_13_steady_speed_depends_on_the_direction(direction: int) -> None:
    got = {}
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        t0, t1, _ = phase(recs, f"L3527_dir{direction:03d}")
        got[side] = mean([v for _, v, _ in truth(side, recs, t1 - 2.0, t1)])
    assert abs(got["sim"] - got["firmware"]) <= 0.08, got


# (leg, speed, table row's "within 5°" range s, peak yaw rate range °/s) for ±30/±90/180°.
HEADING_LEGS = [
    ("v1_01_brg120", 1, (0.57, 0.95), (76, 83)),
    ("v1_03_brg060", 1, (0.57, 0.95), (76, 83)),
    ("v1_05_brg180", 1, (1.27, 1.62), (101, 105)),
    ("v1_07_brg000", 1, (1.27, 1.62), (101, 105)),
    ("v1_09_brg270", 1, (2.40, 2.58), (102, 102)),
    ("v2_01_brg120", 2, (0.56, 0.94), (86, 89)),
    ("v2_03_brg060", 2, (0.56, 0.94), (86, 89)),
    ("v2_05_brg180", 2, (1.03, 1.40), (141, 147)),
    ("v2_07_brg000", 2, (1.03, 1.40), (141, 147)),
    ("v2_09_brg270", 2, (1.98, 2.16), (145, 148)),
]


@pytest.mark.parametrize("name,speed,within5,peak", HEADING_LEGS)
def test_rows_14_15_heading_steps(name: str, speed: int, within5: tuple, peak: tuple) -> None:
    """Within 5° of the new bearing and the peak yaw rate inside the table's range ±20 %
    (the firmware's own legs spread over that range: EKF yaw offsets differ by direction)."""
    for side in SIDES:
        recs = run("heading_steps")[side]
        t0, t1, f = phase(recs, name)
        ys = yaw_series(recs, t0, t1)
        w5 = next(t for t, y, _ in ys if abs(angle_diff(y, f["bearing_deg"])) <= 5.0) - t0
        pk = max(abs(r) for _, _, r in ys)
        slack = 0.2 if side == "sim" else 0.1
        assert within5[0] * (1 - slack) <= w5 <= within5[1] * (1 + slack), (side, w5)
        assert peak[0] * (1 - slack) <= pk <= peak[1] * (1 + slack), (side, pk)


def test_row_18_the_gap_not_the_rate_trips_the_failsafe() -> None:
    for side in SIDES:
        recs = run("setpoint_loss")[side]
        t0, t1, _ = phase(recs, "R_rate_0.8Hz")
        trips = [t for t, s in texts(recs, t0, t1) if s.startswith("Failsafe activated")]
        assert len(trips) >= 5, (side, trips)
        assert mean([v for _, v, _ in truth(side, recs, t1 - 4.0, t1)]) > 1.2, side
        t0, t1, _ = phase(recs, "R_rate_1.0Hz")  # (from 1.5 s: the 0.8 Hz phase's last gap)
        assert not [
            t for t, s in texts(recs, t0 + 1.5, t1) if s.startswith("Failsafe activated")
        ], side


def test_row_19_loss_with_hold_action_loops_back_from_speed() -> None:
    for side in SIDES:
        recs = run("setpoint_loss")[side]
        t0, t1, _ = phase(recs, "L3_silence_hold")
        assert any(m == LOITER and s == 5 for _, m, _, s in heartbeats(recs, t0, t1)), side
        peak = max(abs(r) for _, _, r in yaw_series(recs, t0, t1))
        assert 60.0 <= peak <= 160.0, (side, peak)
        stopped = next(t for t, v, _ in truth(side, recs, t0 + 1.5, t1) if v < 0.05)
        assert 2.5 <= stopped - t0 <= 6.5, (side, stopped - t0)
        t0, t1, _ = phase(recs, "L4_silence_hold")
        ys = [y for _, y, _ in yaw_series(recs, t0, t1)]
        assert max(abs(angle_diff(y, ys[0])) for y in ys) < 5.0, side  # from 1.2 m/s: straight


def test_row_23_hold_while_driving_returns_then_offboard_again() -> None:
    for side in SIDES:
        recs = run("stops")[side]
        t0, t1, _ = phase(recs, "S7_hold_request")
        assert [r for _, r in acks(recs, 176, t0, t0 + 0.5)] == [0], side
        assert all(m == LOITER for _, m, _, _ in heartbeats(recs, t0 + 1.05, t1)), side
        stopped = next(t for t, v, _ in truth(side, recs, t0 + 0.5, t1) if v < 0.05)
        assert 2.5 <= stopped - t0 <= 5.0, (side, stopped - t0)
        t0, t1, _ = phase(recs, "S7_offboard_request")
        assert [r for _, r in acks(recs, 176, t0, t0 + 0.5)] == [0], side
        assert mean([v for _, v, _ in truth(side, recs, t1 - 2.0, t1)]) > 1.5, side


def test_stop_along_the_bearing_keeps_the_heading() -> None:
    """The 0.001 m/s vector along the heading stops from 2 m/s without a swerve (< 2°)."""
    for side in SIDES:
        recs = run("stops")[side]
        t0, t1, _ = phase(recs, "S3_tiny_east")
        ys = yaw_series(recs, t0 - 0.2, t1)
        assert max(abs(angle_diff(y, ys[0][1])) for _, y, _ in ys) < 2.0, side
        assert truth(side, recs, t1 - 1.0, t1)[-1][1] < 0.05, side
