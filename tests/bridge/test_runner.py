"""The deploy runner's loop with an injected clock and a scripted vehicle link."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from openconvoy.bridge.localv2v import LocalBus, LocalV2V
from openconvoy.bridge.runner import EXTRA_COLUMNS, DeployRunner, RunnerOptions
from openconvoy.comms.geodesy import Origin, enu_to_geodetic, geodetic_to_enu
from openconvoy.convoy import ConvoyConfig, SafetyConfig
from openconvoy.core.state import VehicleState
from openconvoy.envs.scenarios import make_scenario
from openconvoy.logs import COLUMNS, read_log
from openconvoy.policies import ClassicalPolicy, load_policy
from openconvoy.testing import WALL0, FakeClock, FakeLink, FixedPolicy


def follower_setup(tmp_path, policy, rate_hz=20.0, duration_s=2.0, safety=None):
    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"), safety=safety or SafetyConfig())
    origin = Origin(*convoy.origin)
    bus = LocalBus()
    leader = LocalV2V(bus)
    link = FakeLink(clock, origin, 1, x=-15.0, y=0.0, move=False)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, rate_hz=rate_hz, duration_s=duration_s, status_period_s=0),
        convoy,
        policy,
        link,
        LocalV2V(bus),
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        log_dir=tmp_path,
        on_status=lambda line: None,
    )
    # The leader is heard once, just now (fresh enough for a 2 s run).
    leader.send(VehicleState(0, clock.wall(), 0.0, 0.0, 1.0, 0.0), clock.wall())
    return clock, link, runner


def test_fixed_rate_absolute_yaw_and_log(tmp_path):
    policy = FixedPolicy(1.0, 0.3)
    clock, link, runner = follower_setup(tmp_path, policy)
    result = runner.run()
    assert result.exit_code == 0 and result.reason == "duration reached"
    # 2 s at 20 Hz, both ends, then the run goes on ticking (stop setpoints, log rows) until
    # the vehicle is at rest: one stop tick, and the tick that sees it at rest.
    assert result.ticks == 43 and result.overruns == 0
    t = np.array([s[0] for s in link.sent])
    drive = link.sent[1:42]  # the first is the stand-still after arming, then 41 drive ticks
    assert np.allclose(np.diff(t[1:44]), 0.05)
    assert [s[1] for s in link.sent[42:]] == [0.0] * (len(link.sent) - 42)
    assert all(s[1] == pytest.approx(1.0) for s in drive)
    # absolute yaw = current heading + heading change (the ideal vehicle turns at once)
    headings = [s[2] for s in drive]
    assert headings[0] == pytest.approx(0.3)
    assert headings[1] == pytest.approx(0.6)
    # HOLD at the end of the run: sent by the tick that saw it at rest, then confirmed by the
    # finish; and disarmed (no --stay-armed).
    assert link.holds == 2 and not link.armed
    log = read_log(tmp_path / "vehicle_1.csv")
    assert len(log["t_s"]) == 43
    assert log["mode"].tolist() == ["coop"] * 41 + ["stop"] * 2  # braking logged, no failsafe
    assert log["speed_mps"][-1] == 0.0 and log["telemetry_valid"].tolist() == [1] * 43
    assert np.allclose(np.diff(log["t_s"]), 0.05)
    with open(tmp_path / "vehicle_1.csv") as f:
        assert tuple(f.readline().strip().split(",")) == COLUMNS + EXTRA_COLUMNS
    meta = json.loads((tmp_path / "vehicle_1.json").read_text())
    assert meta["rate_hz"] == 20.0 and meta["ticks"] == 43 and meta["overruns"] == 0
    assert meta["v2v"]["drop_at"] == "receiver"
    assert meta["t_start_s"] == pytest.approx(WALL0 + 100.0)


def test_fifty_hertz(tmp_path):
    clock, link, runner = follower_setup(
        tmp_path, FixedPolicy(1.0, 0.0), rate_hz=50.0, duration_s=1.0
    )
    assert runner.run().ticks == 51 + 2  # and two ticks braking to rest
    assert np.allclose(np.diff([s[0] for s in link.sent[1:54]]), 0.02)


def test_speed_cap_holds_whatever_the_policy_says(tmp_path):
    clock, link, runner = follower_setup(
        tmp_path, FixedPolicy(4.5, 0.0), safety=SafetyConfig(speed_cap_mps=2.0)
    )
    runner.run()
    speeds = [s[1] for s in link.sent[1:-1]]
    assert speeds and max(speeds) == pytest.approx(2.0)
    log = read_log(tmp_path / "vehicle_1.csv")
    assert np.nanmax(log["cmd_speed_mps"]) == pytest.approx(2.0)


def test_overruns_are_counted_and_the_loop_goes_on(tmp_path):
    clock = None
    policy = FixedPolicy(1.0, 0.0, slow_call=10, slow_s=0.17)
    clock, link, runner = follower_setup(tmp_path, policy)
    policy.clock = clock
    result = runner.run()
    # The 11th tick ran 0.17 s: the next one started 0.12 s (2.4 periods) late, so the
    # slots of 2 ticks passed without one, and that late tick stopped the vehicle.
    assert result.overruns == 2 and result.ticks == 41 - 2 + 2  # + 2 braking to rest
    assert [r for _, r in result.events] == ["control loop late (2.4 periods)"]
    speeds = [s[1] for s in link.sent[1:40]]
    assert speeds.count(0.0) == 1 and speeds.index(0.0) in (10, 11) and set(speeds) == {0.0, 1.0}
    assert result.reason == "duration reached"
    meta = json.loads((tmp_path / "vehicle_1.json").read_text())
    assert (meta["overruns"], meta["late_ticks"]) == (2, 1)
    assert meta["max_tick_late_s"] == pytest.approx(0.12)
    assert meta["failsafe_events"][0]["reason"] == "control loop late (2.4 periods)"
    assert read_log(tmp_path / "vehicle_1.csv")["t_s"].size == result.ticks


def test_the_policy_object_is_used_as_given(tmp_path):
    policy = load_policy("paper")
    assert type(policy) is ClassicalPolicy  # the type `sim` uses
    clock, link, runner = follower_setup(tmp_path, policy)
    assert runner.policy is policy
    runner.run()
    # Standing 15 m behind a leader heard at 1 m/s: PD (0.3, 1.1) on zero spacing error,
    # 1 m/s feed-forward plus 1.1 x the 1 m/s speed difference.
    assert link.sent[1][1] == pytest.approx(2.1, abs=0.05)


def leader_setup(
    tmp_path,
    scenario_spec: str,
    convoy_origin: tuple[float, float, float],
    start_xy: tuple[float, float] | None = None,
):
    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"), origin=convoy_origin)
    origin = Origin(*convoy.origin)
    scenario = make_scenario(scenario_spec, n_followers=1)
    init = scenario.initial_state()
    x, y = float(init.x[0]), float(init.y[0])
    leader_origin = None
    if scenario_spec.startswith("track-file:"):
        leader_origin = scenario.origin
        lat, lon, _ = enu_to_geodetic(scenario.origin, x, y)
        x, y, _ = geodetic_to_enu(origin, lat, lon)  # the same spot in the convoy's frame
    link = FakeLink(clock, origin, 0, x=float(x), y=float(y), heading=float(init.heading[0]))
    runner = DeployRunner(
        RunnerOptions(
            vehicle_id=0, duration_s=3.0, status_period_s=0, leader_waits_for_convoy=False
        ),
        convoy,
        load_policy("paper"),
        link,
        LocalV2V(LocalBus()),
        leader=scenario,
        leader_origin=leader_origin,
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        log_dir=tmp_path,
        on_status=lambda line: None,
    )
    return link, runner


def test_leader_follows_the_paper_scenario(tmp_path):
    link, runner = leader_setup(tmp_path, "paper", ConvoyConfig().origin)
    runner.run()
    t_end = runner.leading.t_finish
    assert t_end is not None  # scenario over: the leader brakes, broadcasting, then ends
    drive = [s for s in link.sent[1:] if s[0] < t_end]
    speeds = np.array([s[1] for s in drive])
    assert np.all(np.diff(speeds) <= 1.0 * 0.05 + 1e-9)  # ramped at the leader's accel limit
    assert speeds[-1] == pytest.approx(1.0)
    assert max(abs(s[2]) for s in drive) < 0.01  # straight east
    assert all(s[1] == 0.0 for s in link.sent if s[0] > t_end)


def test_track_file_leader_steers_in_the_tracks_own_frame(tmp_path):
    # The convoy origin is ~5.6 m south of the track's centre: without converting through
    # lat/lon the leader would believe it is off its path and steer hard.
    convoy_origin = (28.60230, -81.2001, 0.0)
    link, runner = leader_setup(tmp_path, "track-file:example", convoy_origin)
    runner.run()
    drive = [s for s in link.sent[1:] if s[0] < runner.leading.t_finish]
    assert max(abs(s[2]) for s in drive) < 0.05  # along the first straight, east
    assert drive[-1][1] == pytest.approx(1.5, abs=0.3)


def test_passive_leader_broadcasts_but_commands_nothing(tmp_path):
    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"))
    bus = LocalBus()
    ear = LocalV2V(bus)
    link = FakeLink(clock, Origin(*convoy.origin), 0, x=0.0, y=0.0)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=0, passive=True, duration_s=1.0, status_period_s=0),
        convoy,
        load_policy("paper"),
        link,
        LocalV2V(bus),
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        log_dir=tmp_path,
        on_status=lambda line: None,
    )
    assert runner.run().reason == "duration reached"
    assert link.sent == [] and not link.armed and link.holds == 0
    heard = ear.poll(clock.wall())
    assert len(heard) == 11 and all(m.state.vehicle_id == 0 for m in heard)  # 10 Hz for 1 s


def test_passive_is_for_the_leader_only():
    with pytest.raises(ValueError, match="passive"):
        RunnerOptions(vehicle_id=1, passive=True)


def test_connect_timeout_names_the_users_timeout_not_one_attempts(tmp_path):
    # found (input-defects D9): the error said "within 1 s" (one short attempt) after a
    # 5 s --connect-timeout
    from openconvoy.bridge.link import LinkTimeout

    class Silent(FakeLink):
        def connect(self, timeout_s: float) -> None:
            self.clock.sleep(timeout_s)  # nobody answers for the whole attempt
            raise LinkTimeout(f"no heartbeat from a vehicle on udp:x within {timeout_s:g} s")

    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"))
    link = Silent(clock, Origin(*convoy.origin), 1, x=-15.0, y=0.0)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, connect_timeout_s=5.0, status_period_s=0),
        convoy,
        FixedPolicy(1.0, 0.0),
        link,
        LocalV2V(LocalBus()),
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        on_status=lambda line: None,
    )
    result = runner.run()
    assert result.exit_code != 0 and link.sent == []
    assert "within --connect-timeout 5 s" in result.reason and "within 1 s" not in result.reason


@pytest.mark.parametrize(
    "field, value",
    [
        ("rate_hz", math.nan),
        ("rate_hz", 1e6),
        ("rate_hz", math.inf),
        ("connect_timeout_s", math.nan),
        ("arm_timeout_s", -1.0),
        ("duration_s", -5.0),
    ],
)
def test_options_that_would_busy_loop_or_wait_forever_are_refused(field, value):
    # found (issue 10, "What was found" 3): --rate nan flooded the autopilot at ~14 kHz
    with pytest.raises(ValueError, match="out of range"):
        RunnerOptions(vehicle_id=1, **{field: value})
