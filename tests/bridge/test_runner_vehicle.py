"""The runner's vehicle handling with an injected clock: exit codes, a takeover before the
convoy drove, a lost autopilot (no broadcast of an unknown state), ranging passed to the
ladder, HOLD only once braked."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from deploy_harness import make_convoy
from mavlink_edge import EdgeAutopilot

from openconvoy.bridge.localv2v import LocalBus, LocalV2V
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.runner import HOLD_BELOW_MPS, DeployRunner, RunnerOptions
from openconvoy.comms.geodesy import Origin
from openconvoy.convoy import ConvoyConfig, SafetyConfig
from openconvoy.core.state import VehicleState
from openconvoy.logs import read_log
from openconvoy.testing import WALL0, FakeClock, FixedPolicy, ScriptedLink, wait_for, wait_until


def runner_for(tmp_path, link_kw=None, leader_heard=True, duration_s=2.0, safety=None, policy=None):
    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"), safety=safety or SafetyConfig())
    bus = LocalBus()
    leader, ear = LocalV2V(bus), LocalV2V(bus)
    link = ScriptedLink(
        clock, Origin(*convoy.origin), 1, x=-15.0, y=0.0, move=False, **(link_kw or {})
    )
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, duration_s=duration_s, status_period_s=0),
        convoy,
        policy or FixedPolicy(1.0, 0.0),
        link,
        LocalV2V(bus),
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        log_dir=tmp_path,
        on_status=lambda line: None,
    )
    if leader_heard:
        leader.send(VehicleState(0, clock.wall(), 0.0, 0.0, 1.0, 0.0), clock.wall())
    return clock, link, runner, ear


def meta(tmp_path) -> dict:
    return json.loads((tmp_path / "vehicle_1.json").read_text())


def test_a_completed_run_and_a_signal_exit_0(tmp_path):
    _, _, runner, _ = runner_for(tmp_path)
    assert (runner.run().exit_code, meta(tmp_path)["exit_code"]) == (0, 0)
    clock, _, runner, _ = runner_for(tmp_path / "sig", duration_s=None)
    orig = runner.tick
    runner.tick = lambda now: (runner.request_stop("SIGINT") if now > 100.5 else None) or orig(now)
    res = runner.run()
    assert (res.exit_code, res.reason) == (0, "SIGINT")


def test_takeover_before_the_convoy_drove_ends_the_run_nonzero_and_disarms(tmp_path):
    # Nobody heard: the follower waits, armed and still; at t = 100.5 s the mode changes.
    clock, link, runner, _ = runner_for(
        tmp_path, {"takeover_at": 100.5}, leader_heard=False, duration_s=None
    )
    res = runner.run()
    assert res.exit_code == 1
    assert res.reason.startswith("pilot took over before the convoy drove")
    assert "MANUAL" in res.reason and "RC mode switch" in res.reason
    assert clock.t < 100.7  # at once, not when somebody notices
    assert link.disarms == 1 and not link.armed  # standing still: not left armed in MANUAL
    assert all(s[0] < 100.5 and s[1] == 0.0 for s in link.sent)
    m = meta(tmp_path)
    assert m["exit_code"] == 1 and "MANUAL" in m["takeover_reason"]


def test_takeover_after_the_convoy_drove_exits_0_unless_it_was_a_failsafe(tmp_path):
    _, link, runner, _ = runner_for(tmp_path, {"takeover_at": 101.0})
    res = runner.run()
    assert (res.exit_code, res.reason) == (0, "duration reached") and link.disarms == 0
    _, _, runner, _ = runner_for(tmp_path / "fs", {"takeover_at": 101.0, "failsafe": True})
    assert runner.run().exit_code == 1  # PX4's offboard-loss failsafe, say


def test_a_vehicle_outside_the_geofence_is_refused_before_arming(tmp_path):
    # The follower starts 15 m west of the origin, outside a 10 m fence: refused before
    # arming, naming how far out it is (D64: it armed, then latched "geofence").
    _, link, runner, _ = runner_for(tmp_path, safety=SafetyConfig(geofence_radius_m=10.0))
    lines: list[str] = []
    runner.on_status = lines.append
    res = runner.run()
    assert res.exit_code == 2 and not link.armed and link.sent == []
    assert "vehicle 1 is 15 m from the convoy's origin" in res.reason
    assert "outside the 10 m geofence" in res.reason and "not arming" in res.reason
    assert any(line.startswith("vehicle 1: refused: vehicle 1 is 15 m") for line in lines)
    assert not (tmp_path / "vehicle_1.csv").exists()  # refused before the log was opened


def test_lost_autopilot_stops_broadcasting_says_why_and_exits_nonzero(tmp_path):
    clock, link, runner, ear = runner_for(tmp_path, {"freeze_at": 101.0}, duration_s=3.0)
    res = runner.run()
    heard = [m for m in ear.poll(clock.wall()) if m.state is not None and m.state.vehicle_id == 1]
    assert heard  # it broadcast while it knew its state...
    last = max(m.state.t for m in heard)
    # ...and nothing after the loss was detected (0.5 s of silence + up to two ticks).
    assert last <= WALL0 + 101.0 + 0.5 + 0.1 + 1e-9
    assert res.exit_code == 1
    m = meta(tmp_path)
    assert [e["reason"] for e in m["failsafe_events"]][0] == "autopilot link lost"
    (pause,) = m["broadcast_paused"]
    assert pause["why"] == "autopilot link lost" and pause["to_s"] is None
    assert pause["from_s"] == pytest.approx(WALL0 + 101.55, abs=0.06)  # 0.5 s + up to 2 ticks


def test_rangefinder_reading_reaches_the_ladder_centre_to_centre(tmp_path):
    _, link, runner, _ = runner_for(tmp_path, {"range_m": 12.0, "range_rate": -0.3}, duration_s=0.5)
    seen = []
    real = runner.member.supervise

    def spy(action, now, ranging=None):
        seen.append(ranging)
        return real(action, now, ranging)

    runner.member.supervise = spy
    runner.run()
    lengths = runner.member.lengths
    assert seen and all(
        r == pytest.approx((12.0 + 0.5 * (lengths[0] + lengths[1]), -0.3)) for r in seen
    )
    _, _, runner, _ = runner_for(tmp_path / "none", duration_s=0.5)  # no rangefinder
    seen.clear()
    real = runner.member.supervise
    runner.member.supervise = spy
    runner.run()
    assert seen and all(r is None for r in seen)


def test_hold_waits_until_the_stop_setpoints_have_braked_the_vehicle(tmp_path):
    # Moving at 2 m/s, braking at 1 m/s²; the geofence (10 m, it starts 15 m out) latches
    # a stop with HOLD: HOLD only once slower than 0.1 m/s (PX4's Hold would loop back).
    clock, link, runner, _ = runner_for(
        tmp_path,
        {"speed": 2.0, "decel": 1.0},
        safety=SafetyConfig(geofence_radius_m=10.0),
        duration_s=4.0,
    )
    # (a vehicle that starts outside the fence is refused before arming: here it is as if
    # it had driven out of it)
    runner._check_inside_fence = lambda: None
    runner.run()
    first_t, first_v = link.hold_log[0]
    assert first_v < HOLD_BELOW_MPS
    assert first_t >= 100.0 + 1.9  # 2 m/s at 1 m/s²


def test_the_log_shows_only_setpoints_that_went_out(tmp_path):
    # The link refuses from 101 s on (a PX4 whose stream ended): no commanded speed logged.
    _, link, runner, _ = runner_for(tmp_path, {"refuse_at": 101.0}, duration_s=2.0)
    runner.run()
    log = read_log(tmp_path / "vehicle_1.csv")
    t = log["t_s"] - WALL0
    assert np.all(np.isfinite(log["cmd_speed_mps"][t < 100.99]))
    assert np.all(np.isnan(log["cmd_speed_mps"][t >= 101.01]))


def test_a_signal_while_arming_ends_in_hold(tmp_path):
    """The estimator refuses arming for 30 s; GUIDED is already set. A signal then must
    not leave the vehicle in GUIDED: HOLD (and disarm) on the way out."""
    c = make_convoy(tmp_path, n=2, vehicle_config={"ready_after_s": 30.0})
    try:
        follower = c.cars[1]
        wait_until(lambda: follower.vehicle.mode == "GUIDED", 5, "GUIDED requested while arming")
        follower.runner.request_stop("SIGTERM")
        res = follower.join(5.0)
        assert (res.exit_code, res.reason) == (0, "SIGTERM")
        wait_until(lambda: follower.vehicle.mode == "HOLD", 2, "HOLD after the interrupted arming")
        assert not follower.vehicle.armed and follower.link.sent == []
    finally:
        c.stop()


@pytest.mark.timeout(30)
def test_a_signal_after_the_arm_was_accepted_disarms(tmp_path):
    """Armed, then the RC switch sets MANUAL and a signal arrives while GUIDED is asked
    for again: the vehicle is armed although ``prepare_and_arm`` never returned."""
    ap = EdgeAutopilot(
        autopilot="ardupilot", mode_after_arm="MANUAL", mode_switch_repeats=10
    ).start()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"))
    link = MavlinkLink(ap.url, Origin(*convoy.origin), vehicle_id=1, on_status=lambda line: None)
    runner = None

    def status(line: str) -> None:
        if "after arming" in line:
            runner.request_stop("SIGINT")  # the signal lands right now

    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, status_period_s=0, arm_timeout_s=5.0),
        convoy,
        FixedPolicy(1.0, 0.0),
        link,
        LocalV2V(LocalBus()),
        on_status=status,
    )
    try:
        res = runner.run()
        assert (res.exit_code, res.reason) == (0, "SIGINT")
        assert wait_for(lambda: not ap.armed, 1.0)
        modes = [m.param2 for m in ap.messages("COMMAND_LONG") if m.command == 176]
        assert modes[-1] == 4  # HOLD requested on the way out
    finally:
        ap.stop()


def test_distance_sensor_bytes_reach_the_ladder_through_link_and_runner(tmp_path):
    """DISTANCE_SENSOR (forward, 9.00 m) from the autopilot over MAVLink, through
    MavlinkLink and the runner, into the member's ``supervise``, centre to centre."""

    def rangefinder(mav, t):
        mav.distance_sensor_send(int(t * 1000), 10, 2000, 900, 0, 0, 0, 0)

    ap = EdgeAutopilot(autopilot="ardupilot", extra=[rangefinder]).start()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"))
    bus = LocalBus()
    link = MavlinkLink(ap.url, Origin(*convoy.origin), vehicle_id=1, on_status=lambda line: None)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, status_period_s=0, duration_s=1.0),
        convoy,
        FixedPolicy(0.0, 0.0),
        link,
        LocalV2V(bus),
        on_status=lambda line: None,
    )
    seen = []
    real = runner.member.supervise

    def spy(action, frame, ranging=None):
        seen.append(ranging)
        return real(action, frame, ranging)

    runner.member.supervise = spy
    leader = LocalV2V(bus)
    leader.send(VehicleState(0, time.time(), 0.0, 0.0, 0.0, 0.0), time.time())
    try:
        res = runner.run()
    finally:
        ap.stop()
    assert res.reason == "duration reached"
    lengths = runner.member.lengths
    got = [r for r in seen if r is not None]
    assert len(got) >= 0.8 * len(seen) > 10
    assert all(
        r[0] == pytest.approx(9.0 + 0.5 * (lengths[0] + lengths[1])) and abs(r[1]) < 1e-6
        for r in got
    )
