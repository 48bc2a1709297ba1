"""One tick in every world (issue 11): the simulator and the deploy runner drive the member
through ``core.tick`` alike — bit-equal over a whole paper run under loss — and the four
rows where they had drifted (clip, ranging, a non-finite action, no member config) agree."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
import pytest

from openconvoy.bridge.runner import DeployRunner, RunnerOptions
from openconvoy.comms.loss import LossConfig
from openconvoy.convoy import ConvoyConfig
from openconvoy.core import tick as member_tick
from openconvoy.core.member import MemberConfig
from openconvoy.core.state import VehicleState
from openconvoy.envs import ConvoyEnv
from openconvoy.envs.scenarios import make_scenario
from openconvoy.policies import load_policy
from openconvoy.testing import ReplayLink, ReplayV2V
from tests.python_world import python_world  # noqa: F401 - reads the Python world

VEHICLES = ("1/10", "1/6", "1/10")  # the paper scenario's presets


def runner_for(
    vehicle_id: int,
    policy: Any,
    convoy: ConvoyConfig | None = None,
    lengths: list[float] | None = None,
    decels: list[float] | None = None,
):
    clock = [100.0]
    wall = [0.0]
    link, v2v = ReplayLink(clock), ReplayV2V()
    convoy = convoy or ConvoyConfig(name="x", vehicles=VEHICLES)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=vehicle_id, duration_s=1000.0, status_period_s=0),
        convoy,
        policy,
        link,
        v2v,
        lengths=lengths,
        decels=decels,
        clock=lambda: clock[0],
        sleep=lambda s: None,
        wall_clock=lambda: wall[0],
        on_status=lambda line: None,
    )
    return runner, link, v2v, clock, wall


def test_sim_and_runner_give_bit_equal_observations_actions_and_modes_over_a_paper_run_under_loss():
    # The first seed with which follower 2 hears the leader and follower 1 at t = 0 despite
    # 30 % loss, so the runner starts at once, as the simulator does (a runner waits for
    # them, armed and still).
    me = 2
    for seed in range(20):
        env = ConvoyEnv("paper", loss=LossConfig(per=0.3))
        env.reset(seed=seed)
        if all(env.members[me].buffer.latest(v) is not None for v in (0, 1)):
            break
    inboxes: list[list[VehicleState]] = []
    member = env.members[me]
    receive_all = member.receive_all

    def recording_receive_all(inbox: Iterable[VehicleState], now: float) -> None:
        box = list(inbox)
        inboxes[-1].extend(box)
        receive_all(box, now)

    member.receive_all = recording_receive_all  # type: ignore[method-assign]
    policies = {a: load_policy("paper") for a in env.possible_agents}
    for p in policies.values():
        p.reset(0)
    inboxes.append([])
    obs, _ = env.reset(seed=seed)
    sim: list[tuple[VehicleState, list[VehicleState], np.ndarray, np.ndarray, str]] = []
    while env.agents:
        own = member.own
        assert own is not None
        actions = {a: policies[a].act(obs[a]) for a in env.agents}
        frame_obs = obs[f"follower_{me}"]
        box = inboxes[-1]
        inboxes.append([])
        obs, _, _, _, infos = env.step(actions)
        info = infos[f"follower_{me}"]
        applied = np.array(
            [info["cmd_speed_mps"], info["cmd_heading_change_rad"]], dtype=np.float32
        )
        sim.append((own, box, frame_obs, applied, info["mode"]))
    assert len(sim) == 1200
    lost = env.channel.lost_to[me]
    assert lost > 300  # under loss indeed (30 % of ~2400 messages to it)

    scenario = make_scenario("paper")
    lengths = [p.length_m for p in scenario.presets]
    decels = [p.decel_max_mps2 for p in scenario.presets]
    runner, link, v2v, clock, wall = runner_for(
        me, load_policy("paper"), lengths=lengths, decels=decels
    )
    link.state = sim[0][0]
    runner.start()
    for k, (own, box, o, applied, mode) in enumerate(sim):
        clock[0] = 100.0 + k * env.dt
        wall[0] = own.t
        link.state = own
        v2v.inbox = list(box)
        assert runner.tick(clock[0]) == ""
        assert runner.decision is not None, f"tick {k}: the runner did not drive"
        assert runner.frame.observation.tobytes() == o.tobytes(), f"observation differs at tick {k}"
        assert runner.decision.action.tobytes() == applied.tobytes(), f"action differs at tick {k}"
        assert runner.decision.mode == mode, f"mode differs at tick {k}"


def _sim_decide(env: ConvoyEnv, i: int, action, ranging=None) -> member_tick.Decision:
    return member_tick.decide(
        env.members[i], env.sim.frames[i], np.asarray(action), env.sim.bounds[i], ranging
    )


def test_row_clip_before_supervise_in_both_worlds():
    env = ConvoyEnv("paper")
    env.reset(seed=0)
    policy = load_policy("paper")
    runner, link, v2v, clock, wall = runner_for(1, policy)
    # A policy asking for 99 m/s and a 3 rad turn gets the top of the action space in both.
    runner.policy = _Fixed(policy, np.array([99.0, 3.0], dtype=np.float32))
    state = env.members[1].own
    link.state = state
    v2v.inbox = [env.members[0].own]
    runner.start()
    runner.tick(clock[0])
    d = runner.decision
    assert d is not None and d.mode == "coop"
    space = env.action_space("follower_1")
    top = env.presets[1].max_speed_mps  # the 1/6-scale car's
    assert (
        d.action.tolist() == space.high.tolist() == [top, pytest.approx(math.pi / 2)] and top < 99.0
    )
    assert _sim_decide(env, 1, [99.0, 3.0]).action.tobytes() == d.action.tobytes()
    assert _sim_decide(env, 1, [-5.0, -3.0]).action.tolist() == space.low.tolist()


def test_row_a_non_finite_action_is_a_counted_policy_error_and_a_stop_in_both_worlds():
    policy = load_policy("paper")
    env = ConvoyEnv("paper")
    obs, _ = env.reset(seed=0)
    actions = {a: policy.act(o) for a, o in obs.items()}
    actions["follower_1"] = np.array([math.nan, 0.0], dtype=np.float32)
    _, _, _, _, infos = env.step(actions)
    i1 = infos["follower_1"]
    assert (i1["cmd_speed_mps"], i1["mode"], i1["policy_errors"]) == (0.0, "failsafe", 1)
    assert env.safety_events == [(0.0, 1, "policy error: non-finite action nan, 0.0")]
    # Stopped for the rest of the episode, as a vehicle's failsafe latches.
    actions["follower_1"] = np.array([1.0, 0.0], dtype=np.float32)
    _, _, _, _, infos = env.step(actions)
    assert (infos["follower_1"]["cmd_speed_mps"], infos["follower_1"]["mode"]) == (0.0, "failsafe")
    assert infos["follower_2"]["policy_errors"] == 0

    runner, link, v2v, clock, wall = runner_for(
        1, _Fixed(policy, np.array([math.nan, 0.0], dtype=np.float32))
    )
    link.state = VehicleState(1, 0.0, -15.0, 0.0, 0.0, 0.0)
    v2v.inbox = [VehicleState(0, 0.0, 0.0, 0.0, 0.0, 0.0)]
    runner.start()
    runner.tick(clock[0])
    assert runner.decision is not None
    assert runner.decision.policy_error == "non-finite action nan, 0.0"
    assert runner.decision.mode == "stop" and runner.decision.speed_mps == 0.0
    assert runner.failsafes.policy_errors == 1 and "policy error" in runner.failsafes.latched
    assert link.sent[-1] == (0.0, 0.0)


def test_row_a_policy_without_member_config_gets_the_scenario_spacing_in_both_worlds():
    policy = _Fixed(
        load_policy("paper"), np.array([1.0, 0.0], dtype=np.float32), member_config=None
    )
    convoy = ConvoyConfig(name="e", scenario="emergency-braking", vehicles=("full-size",) * 3)
    runner, *_ = runner_for(1, policy, convoy=convoy)
    env = ConvoyEnv("emergency-braking", member_config=policy.member_config)
    assert runner.member.config == env.member_config == MemberConfig(spacing=env.scenario.spacing)
    assert env.scenario.spacing.kind == "constant-time-headway"


def test_row_ranging_reaches_the_ladder_in_both_worlds():
    from openconvoy.core.ladder import LadderConfig
    from openconvoy.core.spacing import SpacingConfig

    cfg = MemberConfig(
        spacing=SpacingConfig("constant-distance", distance_m=20.0),
        ladder=LadderConfig(enabled=True),
    )
    env = ConvoyEnv(
        "emergency-braking", member_config=cfg, vehicle_presets=["full-size", "full-size"]
    )
    env.reset(seed=0)
    cut_in = (8.0, 0.0)  # something 8 m ahead, the predecessor heard 20+ m ahead
    assert _sim_decide(env, 1, [25.0, 0.0], cut_in).mode == "degraded"
    assert _sim_decide(env, 1, [25.0, 0.0]).mode == "coop"
    # The vehicle: the same cut-in seen by its rangefinder (3.2 m bumper to bumper between
    # two 4.8 m cars = 8 m centre to centre) reaches the ladder too.
    policy = _Fixed(
        load_policy("paper"), np.array([25.0, 0.0], dtype=np.float32), member_config=cfg
    )
    convoy = ConvoyConfig(name="e", scenario="emergency-braking", vehicles=("full-size",) * 2)
    runner, link, v2v, clock, wall = runner_for(1, policy, convoy=convoy, lengths=env.sim.lengths)
    link.state = env.members[1].own
    v2v.inbox = [env.members[0].own]
    runner.start()
    runner.tick(clock[0])
    assert runner.decision is not None and runner.decision.mode == "coop"
    link.ranging = (8.0 - 4.8, 0.0)
    clock[0] += 0.05
    runner.tick(clock[0])
    assert runner.decision.mode == "degraded"
    assert (
        runner.decision.action.tobytes()
        == _sim_decide(env, 1, [25.0, 0.0], cut_in).action.tobytes()
    )


class _Fixed:
    """``inner``'s member side and name, always ``action``."""

    def __init__(self, inner: Any, action: np.ndarray, **over: Any) -> None:
        self.member_config = over.get("member_config", inner.member_config)
        self.control_rate_hz = inner.control_rate_hz
        self.name = "fixed"
        self.action = action

    def reset(self, seed: int | None = None) -> None: ...

    def act(self, observation: np.ndarray) -> np.ndarray:
        return self.action


def test_a_policy_missing_a_declared_attribute_is_refused_when_handed_over():
    class Bare:
        def reset(self, seed=None): ...

        def act(self, obs):
            return np.zeros(2, dtype=np.float32)

    from openconvoy.core.errors import ConfigError

    with pytest.raises(ConfigError, match="lacks member_config, control_rate_hz, name"):
        runner_for(1, Bare())


def test_a_rule_changed_in_core_tick_changes_the_vehicle_and_the_simulator_alike(monkeypatch):
    # The vehicle's tick is ``core.tick.tick`` itself, and both worlds decide through the
    # one ``core.tick.decide``: a changed rule there (here: every decision at half speed)
    # reaches the simulator and the vehicle alike.
    decide, tick = member_tick.decide, member_tick.tick
    ticked: list[Any] = []

    def half_speed_decide(*args: Any, **kw: Any) -> member_tick.Decision:
        d = decide(*args, **kw)
        return member_tick.Decision(d.action * np.float32(0.5), d.mode, d.policy_error)

    def spy_tick(member: Any, *args: Any, **kw: Any) -> member_tick.TickResult:
        ticked.append(member)
        return tick(member, *args, **kw)

    monkeypatch.setattr(member_tick, "decide", half_speed_decide)
    monkeypatch.setattr(member_tick, "tick", spy_tick)
    wanted = np.array([2.0, 0.1], dtype=np.float32)
    env = ConvoyEnv("paper")
    obs, _ = env.reset(seed=0)
    policy = load_policy("paper")
    actions = {a: policy.act(o) for a, o in obs.items()}
    actions["follower_1"] = wanted
    runner, link, v2v, clock, wall = runner_for(1, _Fixed(policy, wanted))
    link.state = env.members[1].own
    v2v.inbox = [env.members[0].own]
    _, _, _, _, infos = env.step(actions)
    runner.start()
    assert runner.tick(clock[0]) == ""
    assert ticked == [runner.member]
    d = runner.decision
    assert d is not None and d.mode == "coop"
    assert d.action.tolist() == pytest.approx([1.0, 0.05])
    info = infos["follower_1"]
    assert [info["cmd_speed_mps"], info["cmd_heading_change_rad"]] == d.action.tolist()
    assert link.sent[-1][0] == pytest.approx(1.0)


def _tick_both(actions_for_1: np.ndarray) -> tuple[ConvoyEnv, ReplayV2V, DeployRunner]:
    """One step of the paper convoy's simulator and one tick of follower 1 on a vehicle,
    from the same state."""
    env = ConvoyEnv("paper")
    obs, _ = env.reset(seed=0)
    policy = load_policy("paper")
    actions = {a: policy.act(o) for a, o in obs.items()}
    runner, link, v2v, clock, _ = runner_for(1, _Fixed(policy, actions_for_1))
    link.state = env.members[1].own
    v2v.inbox = [env.members[0].own]
    env.step(actions)
    runner.start()
    assert runner.tick(clock[0]) == ""
    return env, v2v, runner


def test_a_changed_step_or_order_of_steps_in_core_tick_reaches_the_simulator_and_the_vehicle(
    monkeypatch,
):
    # Steps 1 and 2 (τ and the broadcast, then ρ and sensing) run through the one
    # ``core.tick.exchange`` in both worlds: the simulator its whole convoy, the vehicle
    # itself as a world of one (``tick``). A step changed there (here: τ never broadcasts),
    # or the exchange itself replaced, reaches both.
    exchange = member_tick.exchange
    sizes: list[int] = []

    def spy_exchange(members: Any, *args: Any, **kw: Any) -> list[Any]:
        sizes.append(len(members))
        return exchange(members, *args, **kw)

    monkeypatch.setattr(member_tick, "exchange", spy_exchange)
    wanted = np.array([1.0, 0.0], dtype=np.float32)
    env, v2v, _ = _tick_both(wanted)
    assert sizes == [3, 3, 1]  # the simulator's reset and step, then the vehicle's tick
    assert env.members[1].msgs_received > 0 and v2v.counters.sent == 1  # as written

    def mute(member: Any, own: VehicleState, now: float, may_send: bool = True) -> None:
        member.observe_own(own)  # step 1 without τ: nothing is ever broadcast

    monkeypatch.setattr(member_tick, "begin", mute)
    env, v2v, runner = _tick_both(wanted)
    assert sum(env.sim.channel.delivered_to) == 0 and env.members[1].msgs_received == 0
    assert v2v.counters.sent == 0
    assert runner.decision is not None  # the vehicle still sensed and decided


def test_a_follower_waiting_for_its_convoy_senses_and_broadcasts_but_does_not_act():
    acts: list[np.ndarray] = []

    class Counting(_Fixed):
        def act(self, observation: np.ndarray) -> np.ndarray:
            acts.append(observation)
            return self.action

    policy = Counting(load_policy("paper"), np.array([1.0, 0.0], dtype=np.float32))
    runner, link, v2v, clock, wall = runner_for(2, policy)
    link.state = VehicleState(2, 0.0, -30.0, 0.0, 0.0, 0.0)
    v2v.inbox = [VehicleState(0, 0.0, 0.0, 0.0, 0.0, 0.0)]  # follower 1 unheard: waits
    runner.start()
    assert runner.tick(clock[0]) == ""
    assert acts == [] and runner.decision is None
    assert v2v.counters.sent == 1
    assert runner.frame.t == 0.0 and runner.start_gate.t_start is None
    v2v.inbox = [VehicleState(1, 0.05, -15.0, 0.0, 0.0, 0.0)]
    clock[0] += 0.05
    wall[0] = 0.05
    runner.tick(clock[0])
    assert len(acts) == 1 and runner.decision is not None and runner.start_gate.t_start == clock[0]
