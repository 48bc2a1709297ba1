"""ConvoyEnv's compiled tick (``envs.compiled``) against its Python path (``envs.world``).

The same seeds and actions give the same episode on both: observations within float32
rounding, rewards and the plant within 1e-9, infos, terminations and safety events equal.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from pettingzoo.test import api_test, parallel_api_test

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError
from openconvoy.core.policy import PolicyFailure
from openconvoy.envs import ConvoyEnv, convoy_aec_env
from openconvoy.envs.compiled import BACKEND_ENV_VAR, backend_choice
from openconvoy.policies.spec import load_policy
from tests.pinned_warnings import PETTINGZOO_ALLOWED, pinned

FLOAT_INFO_ATOL = 1e-6
"""Infos derived from float32 observations' inputs (spacing error, message age) agree to
float rounding; the plant to 1e-9 m."""


def _episode(steps: int, corrupt=None, **kwargs) -> list:
    """Run both backends on the paper policy's actions; assert they agree every tick;
    return the compiled env's safety events."""
    mc = load_policy("paper").member_config
    fast = ConvoyEnv(member_config=mc, backend="compiled", **kwargs)
    ref = ConvoyEnv(member_config=mc, backend="python", **kwargs)
    assert (fast.backend, ref.backend) == ("compiled", "python")
    assert fast.observation_space("follower_1") == ref.observation_space("follower_1")
    assert fast.action_space("follower_2") == ref.action_space("follower_2")
    of, inf_f = fast.reset(seed=7)
    orf, inf_r = ref.reset(seed=7)
    assert inf_f == inf_r
    policies = {a: load_policy("paper") for a in fast.possible_agents}
    for k in range(steps):
        actions = {a: policies[a].act(of[a]) for a in fast.agents}
        if corrupt is not None:
            actions = corrupt(k, actions)
        of, rf, tf, cf, inf_f = fast.step(actions)
        orf, rr, tr, cr, inf_r = ref.step(actions)
        assert (tf, cf) == (tr, cr), k
        assert np.abs(fast.plant.x - ref.plant.x).max() <= 1e-9, k
        assert np.abs(fast.plant.y - ref.plant.y).max() <= 1e-9, k
        for a in orf:
            assert of[a].dtype == orf[a].dtype == np.float32
            np.testing.assert_allclose(of[a], orf[a], rtol=0, atol=1e-5, err_msg=f"tick {k}")
            assert rf[a] == pytest.approx(rr[a], abs=1e-9)
            assert list(inf_f[a]) == list(inf_r[a])
            for key, want in inf_r[a].items():
                got = inf_f[a][key]
                if isinstance(want, float):
                    assert got == pytest.approx(want, abs=FLOAT_INFO_ATOL), (k, a, key)
                else:
                    assert type(got) is type(want) and got == want, (k, a, key)
        assert fast.safety_events == ref.safety_events, k
        assert fast.forged_rejected == ref.forged_rejected, k
        assert (fast.t, fast.step_count) == (ref.t, ref.step_count)
        if not ref.agents:
            assert not fast.agents
            break
    assert fast.delivery_ratio == pytest.approx(ref.delivery_ratio, abs=0, nan_ok=True)
    return fast.safety_events


def test_paper_episode_under_loss_is_the_python_paths() -> None:
    _episode(1200, loss=LossConfig(per=0.3))


def test_latency_gps_noise_faults_and_refused_actions_as_the_python_path() -> None:
    def corrupt(k: int, actions: dict) -> dict:
        if k == 30:
            actions["follower_1"] = PolicyFailure("policy raised ValueError")
        if k == 40:
            actions["follower_2"] = np.array([np.nan, 0.0])
        return actions

    events = _episode(
        200,
        corrupt=corrupt,
        loss=LossConfig(per=0.2, latency_s=0.03, jitter_s=0.02),
        gps_noise_m=0.5,
        faults=["forge:1@3"],
    )
    reasons = [why for _, _, why in events]
    assert "policy error: policy raised ValueError" in reasons
    assert "policy error: non-finite action nan, 0.0" in reasons


def test_out_of_float32_range_actions_are_clipped_as_the_python_path() -> None:
    def corrupt(k: int, actions: dict) -> dict:
        actions["follower_1"] = np.array([1e39, -1e39])  # finite: clipped, not refused
        return actions

    assert _episode(40, corrupt=corrupt) == []


def test_list_and_integer_actions_as_the_python_path() -> None:
    def corrupt(k: int, actions: dict) -> dict:
        actions["follower_1"] = [4, 0] if k % 2 else [2.5, 0.01]
        actions["follower_2"] = np.array([3, 0], dtype=np.int64)
        return actions

    assert _episode(60, corrupt=corrupt) == []


def test_what_a_caller_keeps_stays_as_it_was_returned() -> None:
    # The compiled tick reuses its arrays; observations, rewards and infos handed out
    # must not change under a caller who keeps them.
    env = ConvoyEnv(loss=LossConfig(per=0.3), backend="compiled")
    kept = [(*env.reset(seed=2), None)]
    action = {a: np.array([4.0, 0.02], dtype=np.float32) for a in env.possible_agents}
    for _ in range(60):
        obs, rewards, _, _, infos = env.step(action)
        kept.append((obs, infos, rewards))
    copies = [
        ({a: o.copy() for a, o in obs.items()}, copy.deepcopy(infos), dict(r or {}))
        for obs, infos, r in kept
    ]
    for _ in range(20):
        env.step(action)
    env.reset(seed=3)
    for (obs, infos, rewards), (obs0, infos0, rewards0) in zip(kept, copies):
        for a in env.possible_agents:
            np.testing.assert_array_equal(obs[a], obs0[a])
        assert infos == infos0 and dict(rewards or {}) == rewards0
    # and they moved: the copies are not all one tick's
    assert kept[1][1]["follower_1"]["t_s"] == 0.05 and kept[-1][1]["follower_1"]["t_s"] == 3.0
    assert not np.array_equal(kept[1][0]["follower_2"], kept[-1][0]["follower_2"])


def test_emergency_braking_collides_or_stops_alike() -> None:
    _episode(400, scenario="emergency-braking", loss=LossConfig(per=0.5))


def test_pettingzoo_checkers_on_the_compiled_tick() -> None:
    with pinned(PETTINGZOO_ALLOWED):
        parallel_api_test(ConvoyEnv(loss=LossConfig(per=0.3), backend="compiled"), num_cycles=300)
        api_test(convoy_aec_env(loss=LossConfig(per=0.3), backend="compiled"), num_cycles=100)


def test_backend_choice_argument_then_environment_then_auto() -> None:
    assert backend_choice(None, {}) == "auto"
    assert backend_choice(None, {BACKEND_ENV_VAR: "python"}) == "python"
    assert backend_choice("compiled", {BACKEND_ENV_VAR: "python"}) == "compiled"
    with pytest.raises(ConfigError, match=BACKEND_ENV_VAR):
        backend_choice(None, {BACKEND_ENV_VAR: "fast"})
    with pytest.raises(ConfigError, match="backend must be one of"):
        backend_choice("numba", {})


def test_auto_takes_the_compiled_tick_where_it_can_and_python_elsewhere(monkeypatch) -> None:
    monkeypatch.delenv(BACKEND_ENV_VAR, raising=False)
    assert ConvoyEnv().backend == "compiled"
    assert ConvoyEnv(render_mode="rgb_array").backend == "python"
    assert ConvoyEnv(plant_presets=["ardupilot-rover"] * 3).backend == "python"
    monkeypatch.setenv(BACKEND_ENV_VAR, "python")
    env = ConvoyEnv()
    assert env.backend == "python" and env.sim.n_vehicles == 3


def test_compiled_env_says_the_world_is_the_python_paths() -> None:
    env = ConvoyEnv(backend="compiled")
    with pytest.raises(AttributeError, match="backend='python'"):
        _ = env.members
    with pytest.raises(ConfigError, match="backend='compiled': rendering"):
        ConvoyEnv(render_mode="rgb_array", backend="compiled")
