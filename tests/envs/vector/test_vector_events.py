"""Safety events in VectorConvoyEnv against ConvoyEnv (``_compare`` of
``test_vector_env`` asserts ``safety_events`` equal at every tick): emergency stops,
injected faults and refused actions, on the fused tick and stage by stage, over convoys
of different seeds and PERs; and an autoreset episode's events kept for the caller."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from test_vector_env import _compare

from openconvoy.comms.loss import LossConfig
from openconvoy.core.faults import parse_fault
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
from openconvoy.envs.vector.events import first_active_step
from openconvoy.policies.spec import load_policy

DT = 1.0 / 20.0  # the control period (s): event times are tick * DT, as the world's clock


def _push(speeds: tuple[float, ...], nan_at: dict[int, tuple[int, int]]):
    """Actions: convoy ``b``'s followers command ``speeds[b]`` m/s straight on (closing
    on the leader); ``nan_at[k] = (b, f)``: follower ``f`` of convoy ``b`` sends NaN at
    tick ``k``."""

    def corrupt(k: int, actions: np.ndarray) -> np.ndarray:
        out = np.zeros_like(actions)
        out[..., 0] = np.asarray(speeds, np.float32)[:, None]
        if k in nan_at:
            out[nan_at[k]] = (np.nan, 0.0)
        return out

    return corrupt


def _kinds(events: list) -> list[tuple[int, str]]:
    return [(v, r.split(":")[0]) for _, v, r in events]


def test_emergency_stops_and_a_refused_action_on_the_fused_tick() -> None:
    assert VectorConvoyEnv(3, loss=LossConfig(per=0.3))._fused is not None
    seen: list = []
    corrupt = _push((2.0, 1.7, 2.3), {60: (1, 1)})
    _compare("paper", B=3, per=[0.0, 0.3, 0.6], steps=500, corrupt=corrupt, events_out=seen)
    stops = [(1, "emergency stop"), (2, "emergency stop")]
    assert _kinds(seen[0]) == _kinds(seen[2]) == stops
    assert _kinds(seen[1]) == [(2, "policy error"), (1, "emergency stop")]
    assert seen[1][0] == (60 * DT, 2, "policy error: non-finite action nan, 0.0")
    # 2.3 - (1 - 0.15): the leader taken as braking at 1 m/s² since its message 0.15 s ago
    # (0.05 s before followers braked while their predecessor was unheard: another run)
    assert "between bumpers closing at 1.45 m/s at 2.30 m/s" in seen[2][0][2]
    assert len({e[0][0] for e in (seen[0], seen[2])}) == 2  # pushed harder: stopped sooner


def test_brake_faults_emergency_stops_and_errors_stage_by_stage() -> None:
    """A halted leader (``_brakes``: the staged tick) and a silent follower; convoy 0's
    follower 1 refuses an infinite action after its emergency stop: both events."""

    def corrupt(k: int, actions: np.ndarray) -> np.ndarray:
        out = _push((2.0, 1.7), {})(k, actions)
        if k == 300:
            out[0, 0] = (np.inf, 0.0)
        return out

    assert VectorConvoyEnv(2, faults=["halt:0@2"])._fused is None
    seen: list = []
    faults = ["halt:0@2", "silent:2@1.03", "halt:0@2"]  # listed twice: one event, as ConvoyEnv
    _compare("paper", B=2, per=[0.2, 0.5], corrupt=corrupt, steps=500, faults=faults,
             events_out=seen)  # fmt: skip
    first = [(21 * DT, 2, "fault silent:2@1.03"), (40 * DT, 0, "fault halt:0@2")]
    assert seen[0][:2] == seen[1][:2] == first
    assert _kinds(seen[0][2:]) == [
        (1, "emergency stop"),
        (2, "emergency stop"),
        (1, "policy error"),
    ]
    assert seen[0][-1] == (300 * DT, 1, "policy error: non-finite action inf, 0.0")
    assert _kinds(seen[1][2:]) == [(1, "emergency stop"), (2, "emergency stop")]


def test_emergency_braking_under_heavy_loss() -> None:
    """Full-size cars told 6 m/s faster than their policy: one convoy of the two stops (8 m/s
    stopped both once the rule assumed the predecessor may brake, issue 22)."""
    seen: list = []
    faster = np.array([6.0, 0.0], np.float32)
    _compare("emergency-braking", B=2, per=0.9, events_out=seen, corrupt=lambda k, a: a + faster)
    assert seen[0] == [] and _kinds(seen[1]) == [(2, "emergency stop")]


def test_an_autoreset_episodes_events_stay_in_the_final_infos() -> None:
    B, loss = 2, LossConfig(per=0.3)
    mc = load_policy("paper").member_config
    kw = {"member_config": mc, "loss": loss, "max_time_s": 2.0, "faults": ["halt:0@1"]}
    vec = VectorConvoyEnv(B, "paper", **kw)
    envs = [ConvoyEnv("paper", **kw) for _ in range(B)]
    vec.reset(seed=5)
    for b, e in enumerate(envs):
        e.reset(seed=5 + b)
    for k in range(vec.max_steps):
        actions = np.tile(np.array([1.0, 0.0], np.float32), (B, 2, 1))
        if k == 7:
            actions[1, 0] = (np.nan, np.nan)
        _, _, _, trunc, info = vec.step(actions)
        for b, e in enumerate(envs):
            e.step({a: actions[b, j] for j, a in enumerate(e.possible_agents)})
    assert trunc.all() and sorted(info["final_safety_events"]) == [0, 1]
    for b, e in enumerate(envs):
        assert info["final_safety_events"][b] == e.safety_events
    refused = (7 * DT, 1, "policy error: non-finite action nan, nan")
    assert info["final_safety_events"][1][0] == refused
    assert info["final_safety_events"][0] == [(1.0, 0, "fault halt:0@1")]
    assert vec.safety_events(0) == vec.safety_events(1) == []  # the new episodes' (t = 0)


def test_without_faults_only_the_convoys_with_latches_build_events() -> None:
    vec = VectorConvoyEnv(3, "paper", max_time_s=0.5)
    vec.reset(seed=1)
    for k in range(vec.max_steps):
        actions = np.ones((3, 2, 2), np.float32)
        if k == 2:
            actions[2, 1, 1] = np.inf
        _, _, _, trunc, info = vec.step(actions)
    refused = (2 * DT, 2, "policy error: non-finite action 1.0, inf")
    assert trunc.all() and info["final_safety_events"] == {0: [], 1: [], 2: [refused]}
    assert vec.events.count.tolist() == [0, 0, 0]  # reset with the new episodes


def test_a_faults_first_tick_is_the_worlds() -> None:
    for spec, dt, k in (("halt:0@0", 0.05, 0), ("halt:0@1", 0.05, 20), ("dead:1@6.03", 0.05, 121),
                        ("silent:0@0.3", 0.1, 3), ("halt:0@0.30000000001", 0.1, 3)):  # fmt: skip
        f = parse_fault(spec)
        assert first_active_step(f, dt) == k, spec
        assert f.active(k * dt) and (k == 0 or not f.active((k - 1) * dt))


def test_a_dead_predecessor_still_stops_a_creeping_follower() -> None:
    """Follower 1 dead at 3 s, the followers creeping 2 m/s over the policy: past the stop
    age the braking rule still sees it (``ConvoyMember.gap_estimate``), in both worlds."""
    seen: list = []
    creep = np.array([2.0, 0.0], np.float32)
    _compare("emergency-braking", B=2, per=[0.0, 0.3], faults=["dead:1@3"], events_out=seen,
             corrupt=lambda k, a: a + creep)  # fmt: skip
    for events in seen:
        assert _kinds(events) == [(1, "fault dead"), (2, "emergency stop")]
        assert events[1][0] > 5.0  # after the estimate expired as a target (stop age 2 s)


def test_the_track_leader_stops_for_the_stopped_tail_in_both_worlds() -> None:
    """D49 (issue 22): follower 1 halts at 10 s; the leader laps the track and stops short
    of the convoy's tail by the same rule, the same tick, in both worlds."""
    seen: list = []
    _compare("track", B=1, per=0.0, faults=["halt:1@10"], events_out=seen, steps=1650)
    stops = [e for e in seen[0] if e[1] == 0 and e[2].startswith("emergency stop")]
    assert len(stops) == 1 and 70.0 < stops[0][0] < 82.0
