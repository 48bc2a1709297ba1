"""Each failsafe provoked for real against simulated MAVLink vehicles.

Every test checks, on the setpoints actually sent, that motion stops within 0.5 s of the
detection (the issue's number), and that the log survives (CSV rows and metadata JSON).
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from deploy_harness import make_convoy, replace_safety

from openconvoy.bridge.simvehicle.vehicle import SimVehicle
from openconvoy.logs import read_log
from openconvoy.policies import load_policy
from openconvoy.testing import wait_until

STOP_WITHIN_S = 0.5


def moving(car, speed: float = 0.5) -> bool:
    return car.vehicle.state().speed > speed


def assert_stopped_after(car, t_detect: float) -> None:
    """Setpoints from 0.5 s after detection on are all speed 0, and one went out in time;
    and the vehicle itself came to rest."""
    late = car.link.after(t_detect + STOP_WITHIN_S)
    assert all(s[1] == 0.0 for s in late), f"motion commanded after detection: {late[:3]}"
    sent = car.link.after(t_detect - 1e-3)
    if sent:  # (a taken-over vehicle is sent nothing at all)
        # A tick already under way at detection may still send its motion setpoint; the
        # first stop setpoint must follow within 0.5 s.
        stops = [s for s in sent if s[1] == 0.0]
        assert stops and stops[0][0] - t_detect <= STOP_WITHIN_S, sent[:2]
    wait_until(lambda: abs(car.vehicle.state().speed) < 0.05, 4.0, "vehicle at rest")


def assert_log_survived(convoy, vid: int, mode: str = "failsafe") -> dict:
    log = read_log(convoy.log_dir / f"vehicle_{vid}.csv")
    assert len(log["t_s"]) > 10
    assert mode in set(log["mode"].tolist())
    meta = json.loads((convoy.log_dir / f"vehicle_{vid}.json").read_text())
    assert meta["vehicle_id"] == vid
    return meta


def test_frozen_telemetry_stops_then_holds_when_it_returns(tmp_path):
    c = make_convoy(tmp_path, n=2)
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        t_freeze = time.monotonic()
        follower.vehicle.freeze(True)
        t_detect = wait_until(lambda: follower.runner.failsafes.events, 3, "link-loss detection")
        det = follower.first_event("autopilot link lost")
        assert 0.45 <= det - t_freeze <= 0.5 + 0.3  # 0.5 s of silence (+ a tick, loaded CI)
        time.sleep(0.8)
        assert_stopped_after(follower, det)
        assert t_detect >= det
        follower.vehicle.freeze(False)  # the link returns: HOLD, no more commands
        wait_until(lambda: follower.vehicle.mode == "HOLD", 4, "HOLD after the link returned")
        # The runner learns the mode from the next 1 Hz heartbeat, then goes quiet.
        wait_until(
            lambda: follower.runner.vehicle.tel.mode == "HOLD", 2.5, "HOLD seen by the runner"
        )
        n_sent = len(follower.link.sent)
        time.sleep(0.5)
        assert len(follower.link.sent) - n_sent <= 2  # quiet once held
        assert follower.vehicle.mode == "HOLD"
    finally:
        c.stop()
    meta = assert_log_survived(c, 1)
    assert [e["reason"] for e in meta["failsafe_events"]][:2] == [
        "autopilot link lost",
        "autopilot link returned after a loss",
    ]


def test_killed_vehicle_stops_and_rebooted_one_is_left_alone(tmp_path):
    c = make_convoy(tmp_path, n=2)
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        cfg = follower.vehicle.config
        follower.vehicle.stop()  # killed: socket closed, nothing more from it
        det = wait_until(lambda: follower.runner.failsafes.events, 3, "detection")
        det = follower.first_event("autopilot link lost")
        time.sleep(0.7)
        late = follower.link.after(det + STOP_WITHIN_S)
        assert late and all(s[1] == 0.0 for s in late)  # keeps commanding a stop, reconnecting
        # The autopilot reboots on the same port, disarmed and in HOLD: a mode we did not
        # ask for, so the runner treats it as somebody else's vehicle now and commands
        # nothing more; it never re-arms it or switches it back to GUIDED.
        reborn = SimVehicle(f"udpin:127.0.0.1:{follower.port}", cfg).start()
        c.extra.append(reborn)
        t_reborn = time.monotonic()
        wait_until(
            lambda: follower.runner.failsafes.took_over, 6, "runner sees the rebooted vehicle"
        )
        t_seen = follower.first_event("pilot took over")
        time.sleep(1.0)
        assert all(s[1] == 0.0 for s in follower.link.after(t_reborn))
        assert follower.link.after(t_seen) == []
        assert (
            reborn.mode == "MANUAL" and not reborn.armed and reborn.state().speed == 0.0
        )  # INITIAL_MODE
    finally:
        c.stop()
    assert_log_survived(c, 1)


def test_lost_tcp_link_stops_and_keeps_reconnecting(tmp_path):
    c = make_convoy(tmp_path, n=2, tcp=True)
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        cfg = follower.vehicle.config
        follower.vehicle.stop()  # the TCP peer closes: EOF, a lost link
        wait_until(lambda: follower.link.lost, 3, "EOF seen")
        det = wait_until(lambda: follower.runner.failsafes.events, 2, "detection")
        det = follower.first_event("autopilot link lost")
        time.sleep(4.5)
        assert len(follower.link.reconnects) >= 2  # every 2 s while lost
        assert all(s[1] == 0.0 for s in follower.link.after(det))
        reborn = SimVehicle(f"tcpin:127.0.0.1:{follower.port}", cfg).start()
        c.extra.append(reborn)
        wait_until(lambda: not follower.link.lost, 6, "reconnected")
        # Back, disarmed and in MANUAL (ArduPilot's INITIAL_MODE, not asked for): left alone.
        wait_until(lambda: follower.runner.failsafes.took_over, 4, "rebooted vehicle seen")
        assert reborn.mode == "MANUAL" and not reborn.armed
    finally:
        c.stop()
    assert_log_survived(c, 1)


def test_silent_predecessor_ladder_degrades_then_stops_and_holds(tmp_path):
    c = make_convoy(tmp_path, n=2, policy="paper+ladder")
    try:
        leader, follower = c.cars
        wait_until(lambda: moving(follower), 15, "follower moving")
        leader.v2v.send = lambda state, now: False  # the predecessor's radio goes silent
        t_silent = time.monotonic()
        wait_until(lambda: follower.runner.member.mode == "degraded", 2, "degraded mode")
        wait_until(lambda: follower.runner.member.mode == "stop", 4, "stop rung")
        t_stop = time.monotonic()
        # stop_after_s = 2 s after the last message was measured: that is up to one
        # broadcast period (0.1 s) plus a tick (0.05 s) before the radio went silent.
        assert 2.0 - 0.15 <= t_stop - t_silent <= 2.0 + 0.5
        time.sleep(0.8)
        assert_stopped_after(follower, t_stop)
        # Issue 10: a staleness stop once left the vehicle in GUIDED; now it holds.
        wait_until(lambda: follower.vehicle.mode == "HOLD", 3, "HOLD after the staleness stop")
        assert follower.first_event("staleness ladder stop") >= t_silent
        leader.v2v.send = type(leader.v2v).send.__get__(leader.v2v)  # radio back
        wait_until(lambda: follower.runner.member.mode == "coop", 2, "member back to coop")
        time.sleep(0.5)
        assert (
            follower.vehicle.mode == "HOLD" and follower.vehicle.state().speed < 0.05
        )  # stays held
    finally:
        c.stop()
    log = read_log(c.log_dir / "vehicle_1.csv")
    assert {"coop", "degraded", "failsafe"} <= set(log["mode"].tolist())


def test_silent_predecessor_without_ladder_hits_the_bridge_backstop(tmp_path):
    c = make_convoy(tmp_path, n=2, safety=replace_safety(max_msg_age_s=1.0))
    try:
        leader, follower = c.cars
        wait_until(lambda: moving(follower), 15, "follower moving")
        leader.v2v.send = lambda state, now: False
        t_silent = time.monotonic()
        wait_until(
            lambda: follower.runner.gate.last_reason == "messages needed are stale", 3, "backstop"
        )
        t_det = time.monotonic()
        assert t_det - t_silent <= 1.0 + 0.5
        time.sleep(0.8)
        assert_stopped_after(follower, t_det)
        wait_until(lambda: follower.vehicle.mode == "HOLD", 3, "HOLD after the backstop")
    finally:
        c.stop()
    assert_log_survived(c, 1)


class RaisingPolicy:
    """The paper policy, raising from its ``fail_after``-th call on."""

    def __init__(self, fail_after: int) -> None:
        self.inner = load_policy("paper")
        self.member_config = self.inner.member_config
        self.control_rate_hz = self.inner.control_rate_hz
        self.name = "raising"
        self.calls = 0
        self.fail_after = fail_after
        self.t_first_raise: float | None = None

    def reset(self, seed=None) -> None:
        self.inner.reset(seed)

    def act(self, obs):
        self.calls += 1
        if self.calls >= self.fail_after:
            if self.t_first_raise is None:
                self.t_first_raise = time.monotonic()
            raise RuntimeError("policy bug")
        return self.inner.act(obs)


def test_policy_exception_stops_logs_and_keeps_looping(tmp_path):
    policy = RaisingPolicy(fail_after=10**9)
    c = make_convoy(tmp_path, n=2, policies={1: policy})
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        policy.fail_after = policy.calls + 1
        wait_until(lambda: policy.t_first_raise is not None, 2, "policy raised")
        # The runner records the failsafe right after act() raised, on its own thread.
        wait_until(
            lambda: any(r.startswith("policy error") for _, r in follower.runner.failsafes.events),
            1,
            "policy error recorded",
        )
        det = follower.first_event("policy error")
        ticks = follower.runner.timer.ticks
        time.sleep(1.0)
        assert follower.runner.timer.ticks - ticks >= 10  # the loop goes on
        assert_stopped_after(follower, det)
        assert follower.vehicle.mode == "GUIDED"  # a stop, not a HOLD: a person decides
    finally:
        c.stop()
    meta = assert_log_survived(c, 1)
    assert meta["policy_errors"] >= 10
    assert any(
        e["reason"] == "policy error: RuntimeError: policy bug" for e in meta["failsafe_events"]
    )


def test_geofence_holds_whatever_the_policy_says(tmp_path):
    # The leader starts at the origin and drives east: a 3 m fence stops it after ~2 m.
    # (The follower, 15 m out, would be refused before arming: it runs dry, broadcasting.)
    c = make_convoy(
        tmp_path,
        n=2,
        safety=replace_safety(geofence_radius_m=3.0),
        options={1: {"dry_run": True}},
    )
    try:
        leader = c.cars[0]
        wait_until(lambda: leader.runner.failsafes.latched == "geofence", 20, "geofence")
        det = leader.first_event("geofence")
        time.sleep(0.8)
        assert_stopped_after(leader, det)
        wait_until(lambda: leader.vehicle.mode == "HOLD", 3, "HOLD")
        x = leader.vehicle.state().x
        assert x < 3.0 + 0.5  # braking at 1 m/s² from ~1 m/s, stopped near the fence
    finally:
        c.stop()
    assert_log_survived(c, 0)


def test_measured_gap_below_minimum_is_an_emergency_stop(tmp_path):
    c = make_convoy(tmp_path, n=2)
    try:
        leader, follower = c.cars
        wait_until(lambda: moving(follower), 15, "follower moving")
        # The predecessor reports itself 0.6 m ahead of the follower (a real near-miss
        # would look the same to the follower).
        own = follower.runner.member.own
        ghost = type(own)(
            vehicle_id=0,
            t=time.time(),
            x=own.x + 0.6,
            y=own.y,
            speed=own.speed,
            heading=own.heading,
        )
        c.bus.publish(leader.v2v._q, ghost)
        wait_until(lambda: follower.runner.failsafes.latched.startswith("gap"), 2, "e-stop")
        det = follower.first_event("gap")
        time.sleep(0.8)
        assert_stopped_after(follower, det)
        wait_until(lambda: follower.vehicle.mode == "HOLD", 3, "HOLD")
    finally:
        c.stop()
    assert_log_survived(c, 1)


def test_pilot_takeover_stops_commanding_and_never_switches_back(tmp_path):
    c = make_convoy(tmp_path, n=2)
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        follower.vehicle.pilot_set_mode("MANUAL")
        wait_until(lambda: follower.runner.failsafes.took_over, 3, "takeover seen")
        det = follower.first_event("pilot took over")
        time.sleep(1.5)
        assert follower.link.after(det) == []  # not one setpoint after it was seen
        assert follower.vehicle.mode == "MANUAL"  # and no switching back
        assert follower.link.holds == []
    finally:
        c.stop()
    assert follower.vehicle.mode == "MANUAL"  # not even at exit
    assert_log_survived(c, 1)


def test_convoy_abort_stops_every_member_holds_and_saves_logs(tmp_path):
    c = make_convoy(tmp_path, n=3)
    try:
        wait_until(lambda: all(moving(car) for car in c.cars), 15, "convoy moving")
        c.bus.abort()
        for car in c.cars:
            res = car.join(5.0)
            assert res.exit_code == 0 and res.reason == "convoy abort"
            det = car.first_event("convoy abort")
            assert_stopped_after(car, det)
            assert car.vehicle.mode == "HOLD"
    finally:
        c.stop()
    for vid in range(3):
        assert_log_survived(c, vid)


def test_request_stop_is_what_signals_do(tmp_path):
    c = make_convoy(tmp_path, n=2)
    try:
        follower = c.cars[1]
        wait_until(lambda: moving(follower), 15, "follower moving")
        t = time.monotonic()
        follower.runner.request_stop("SIGTERM")
        res = follower.join(5.0)
        assert res.exit_code == 0 and res.reason == "SIGTERM"
        assert_stopped_after(follower, t)
        assert follower.vehicle.mode == "HOLD"
    finally:
        c.stop()
    assert_log_survived(c, 1)


def test_dry_run_never_arms_nor_sends_setpoints_but_logs_and_broadcasts(tmp_path):
    c = make_convoy(tmp_path, n=2, options={1: {"dry_run": True}})
    try:
        leader, follower = c.cars
        wait_until(lambda: moving(leader), 15, "leader moving")
        time.sleep(1.0)
        assert follower.link.sent == [] and follower.vehicle.setpoints_received == 0
        assert not follower.vehicle.armed
        assert follower.runner.member.msgs_sent > 5
        assert np.isfinite(follower.runner.frame.spacing_error_m)
    finally:
        c.stop()
    log = read_log(c.log_dir / "vehicle_1.csv")
    assert np.all(np.isnan(log["cmd_speed_mps"]))  # nothing was commanded
    assert json.loads((c.log_dir / "vehicle_1.json").read_text())["dry_run"] is True


def test_followers_wait_still_until_they_hear_the_convoy(tmp_path):
    c = make_convoy(tmp_path, n=2, start=False)
    try:
        leader, follower = c.cars
        follower.start()
        # Armed (confirmed by the next 1 Hz heartbeat), then a second of the loop.
        wait_until(lambda: len(follower.link.sent) >= 20, 10, "follower looping")
        assert follower.vehicle.armed and follower.vehicle.mode == "GUIDED"
        assert all(s[1] == 0.0 for s in follower.link.sent)
        assert follower.vehicle.state().speed == 0.0
        heading = follower.vehicle.state().heading
        assert all(abs(s[2] - heading) < 1e-3 for s in follower.link.sent)  # yaw = own heading
        leader.start()
        wait_until(lambda: moving(follower), 15, "follower follows")
    finally:
        c.stop()


@pytest.mark.parametrize("autopilot", ["px4"])
def test_px4_streams_before_offboard_and_loses_offboard_when_the_stream_stops(tmp_path, autopilot):
    stall = threading.Event()

    c = make_convoy(tmp_path, n=2, autopilot=autopilot, start=False)
    follower = c.cars[1]
    real_sleep = follower.runner.sleep

    def sleep(s: float) -> None:
        if stall.is_set():
            stall.clear()
            real_sleep(2.5)  # the loop hangs: the setpoint stream stops for 2.5 s
        real_sleep(s)

    follower.runner.sleep = sleep
    for car in c.cars:
        car.start()
    try:
        wait_until(lambda: moving(follower), 20, "follower moving under OFFBOARD")
        # The simulated PX4, as the real one, refuses arming in OFFBOARD without a setpoint
        # stream (shared/sitl-px4 rows 3-5): being here means they streamed first.
        assert follower.vehicle.mode == "OFFBOARD" and follower.vehicle.armed
        stall.set()
        # PX4 leaves OFFBOARD 1 s after the last setpoint (COM_OF_LOSS_T) for POSCTL and
        # brakes (shared/sitl-px4 row 16); the runner sees a mode it did not ask for and
        # never takes the vehicle back.
        wait_until(lambda: follower.vehicle.mode == "POSCTL", 4, "PX4 offboard-loss failsafe")
        wait_until(lambda: follower.runner.failsafes.took_over, 4, "runner sees it")
        det = follower.first_event("pilot took over")
        time.sleep(1.0)
        assert follower.link.after(det) == []
        assert follower.vehicle.mode == "POSCTL" and follower.link.setpoints.ended  # never resumed
        assert follower.runner.timer.overruns >= 1  # the stall was counted
    finally:
        c.stop()
    meta = assert_log_survived(c, 1)
    assert meta["autopilot"] == "px4" and meta["overruns"] >= 1


def test_a_signal_while_waiting_to_arm_ends_the_run_cleanly(tmp_path):
    # The estimator is not ready for 30 s (a real Rover needs ~40 s after boot).
    c = make_convoy(tmp_path, n=2, vehicle_config={"ready_after_s": 30.0})
    try:
        follower = c.cars[1]
        time.sleep(1.5)
        assert follower.thread.is_alive() and not follower.vehicle.armed
        t = time.monotonic()
        follower.runner.request_stop("SIGTERM")
        res = follower.join(5.0)
        assert time.monotonic() - t < 2.5  # at the next arming retry, not after 30 s
        assert (res.exit_code, res.reason) == (0, "SIGTERM")
        assert not follower.vehicle.armed and follower.link.sent == []
    finally:
        c.stop()


def test_arming_refused_until_timeout_names_the_autopilots_reason(tmp_path):
    c = make_convoy(
        tmp_path, n=2, vehicle_config={"ready_after_s": 30.0}, options={1: {"arm_timeout_s": 4.0}}
    )
    # 4 s: GUIDED is confirmed by the 1 Hz heartbeat before the first arm attempt (seen
    # timing out first with 1.5 s on a loaded machine); arming stays refused until 30 s.
    try:
        res = c.cars[1].join(10.0)
        assert res.exit_code == 1
        assert "MAV_CMD_COMPONENT_ARM_DISARM" in res.reason
        # The firmware's refusal text: its IMU checks while they last, then the AHRS one until
        # 30 s; which one the last attempt met depends on how fast a loaded machine booted
        # the simulated vehicle (a clean CI run once saw "Accels inconsistent").
        texts = (
            "AHRS: not using configured AHRS type",
            "Accels inconsistent",
            "Gyros inconsistent",
        )
        assert any(f"Arm: {t}" in res.reason for t in texts), res.reason
        assert c.cars[1].link.sent == []  # nothing was commanded
    finally:
        c.stop()
