"""shared/sitl-px4/README.md's conformance table: recordings of real PX4 (SIH rover)
replayed into the simulated PX4 vehicle; the same measurement on both sides. Headings
and speeds come from the firmware's EKF telemetry (ATTITUDE, GLOBAL_POSITION_INT)."""

from __future__ import annotations

import pytest
from conformance import (
    acks,
    angle_diff,
    circular_mean,
    heartbeats,
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
        assert any(b & 128 and m == OFFBOARD and b == 145 for _, m, b, _ in heartbeats(recs, t0, t1)), side


def test_row_06_offboard_while_armed_needs_the_stream() -> None:
    for side in SIDES:
        recs = run("boot_and_arm")[side]
        t0, t1, _ = phase(recs, "E2_offboard_armed_no_setpoints")
        assert [r for _, r in acks(recs, 176, t0, t1)] == [1], side
        assert any(s.startswith("Switching to Offboard is currently not available")
                   for _, s in texts(recs, t0, t1)), side


@pytest.mark.parametrize("case", ["L3527", "L2503yaw+90", "G6_3527", "G6_2503yaw+90"])
@pytest.mark.parametrize("direction", [0, 45, 90, 135, 180, 225, 270, 315])
def test_row_07_velocity_sets_the_bearing_and_the_yaw_field_is_ignored(case: str, direction: int) -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        t0, t1, _ = phase(recs, f"{case}_dir{direction:03d}")
        yaw = circular_mean([y for _, y, _ in yaw_series(recs, t1 - 1.0, t1)])
        assert abs(angle_diff(yaw, direction)) <= 1.5, (side, yaw)


def test_row_10_local_offset_ned_is_rejected_with_a_text() -> None:
    for side in SIDES:
        recs = run("setpoint_semantics")[side]
        said = [s for _, s in texts(recs) if "coordinate frame 7 unsupported" in s]
        assert said and said[0].startswith("SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported"), side


@pytest.mark.parametrize("name", ["L1_silence", "L2_silence"])
def test_rows_16_17_offboard_loss_failsafe_and_return(name: str) -> None:
    fw = run("setpoint_loss")["firmware"]
    t0, t1, _ = phase(fw, name)
    last = max(r["t"] for r in fw if r["dir"] == "tx" and r["type"].startswith("SET_POSITION") and r["t"] < t0 + 0.01)
    for side in SIDES:
        recs = run("setpoint_loss")[side]
        fs = next(t for t, s in texts(recs, t0 - 0.2, t1) if s.startswith("Failsafe activated"))
        assert 1.0 <= fs - last <= 1.15, (side, fs - last)
        beats = heartbeats(recs, fs + 0.8, t1)
        assert all(m == POSCTL and b & 128 and s == 5 for _, m, b, s in beats), (side, beats)
        ys = [y for _, y, _ in yaw_series(recs, last, t1)]
        assert max(abs(angle_diff(y, ys[0])) for y in ys) < 2.0, side  # a straight brake
        r0, r1, _ = phase(recs, name.replace("silence", "resume"), 0) if False else (t1, t1 + 3.0, None)
        assert any(m == OFFBOARD for _, m, _, _ in heartbeats(recs, r0, r0 + 1.5)), side


@pytest.mark.parametrize("name,toward", [("S9_project_stop_yaw90.5", "south"), ("S10_project_stop_yaw89.5", "north"),
                                         ("S2_zero_2503_yaw90", "north")])
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
        ratio = (b["fields"]["time_boot_ms"] - a["fields"]["time_boot_ms"]) / 1000.0 / (b["t"] - a["t"])
        assert abs(ratio - 0.990) <= 0.003, (side, ratio)
