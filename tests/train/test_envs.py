"""Training environments: SB3's checker on the single-agent view, the parameter-sharing
VecEnv (shapes, episode ends, seeding) and domain randomization."""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
import pytest
from stable_baselines3.common.env_checker import check_env

from openconvoy.comms.loss import LossConfig
from openconvoy.envs import SINGLE_AGENT_ID, ConvoyEnv
from openconvoy.envs.vehicles import VEHICLE_PRESETS, preset_to_toml
from openconvoy.policies import load_policy
from openconvoy.policies.presets import PRESETS
from openconvoy.train.randomization import (
    PLANT_JITTER_FIELDS,
    EnvSpec,
    Randomization,
    RandomizedConvoyEnv,
    draw_world,
)
from openconvoy.train.vecenv.shared import shared_policy_vec_env
from tests.pinned_warnings import GYMNASIUM_ALLOWED, pinned


def test_sb3_check_env_passes_on_the_single_agent_view() -> None:
    env = gymnasium.make(SINGLE_AGENT_ID)
    with pinned(GYMNASIUM_ALLOWED):
        check_env(env.unwrapped, warn=True, skip_render_check=True)
        check_env(env, warn=True, skip_render_check=True)


def _vec(
    n_envs: int = 3,
    max_time_s: float = 1.0,
    n_followers: int = 2,
    randomization: Randomization | None = None,
):
    spec = EnvSpec(n_followers=n_followers, max_time_s=max_time_s)
    return shared_policy_vec_env(
        lambda: RandomizedConvoyEnv(spec, randomization or Randomization()), n_envs
    )


def _rollout(venv, seed: int, steps: int, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    venv.seed(seed)
    obs = [venv.reset()]
    rewards = []
    for _ in range(steps):
        o, r, _, _ = venv.step(actions)
        obs.append(o)
        rewards.append(r)
    return np.array(obs), np.array(rewards)


def test_shared_vec_env_has_a_slot_per_follower_per_env() -> None:
    venv = _vec(n_envs=3, n_followers=2, randomization=Randomization(per_range=(0.0, 0.0)))
    size = PRESETS["paper"].member.layout.size
    assert venv.num_envs == 6
    assert venv.observation_space.shape == (size,)
    assert venv.action_space.shape == (2,) and venv.action_space.low.min() == -1.0
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (6, size) and obs.dtype == np.float32
    for _ in range(5):  # long enough for the randomized latency to deliver a message
        o, r, d, infos = venv.step(np.zeros((6, 2), dtype=np.float32))
    assert o.shape == (6, size) and r.shape == (6,) and d.shape == (6,) and len(infos) == 6
    # Slot j is follower j % 2 + 1 of env j // 2: only follower 2 has a second predecessor.
    pred_2_valid = PRESETS["paper"].member.layout.slot_offset("pred_2") + 6
    assert [bool(x) for x in o[:, pred_2_valid] > 0.5] == [False, True] * 3


def test_episodes_end_together_and_restart() -> None:
    venv = _vec(n_envs=2, max_time_s=1.0)  # 20 ticks at 20 Hz
    venv.seed(1)
    venv.reset()
    for step in range(1, 21):
        _, _, dones, infos = venv.step(np.zeros((4, 2), dtype=np.float32))
        if step < 20:
            assert not dones.any()
    assert dones.all()
    for info in infos:
        assert info["TimeLimit.truncated"] is True
        assert info["terminal_observation"].shape == venv.observation_space.shape
    # The next step belongs to a fresh episode (time restarts).
    _, _, dones, infos = venv.step(np.zeros((4, 2), dtype=np.float32))
    assert not dones.any() and infos[0]["t_s"] == pytest.approx(0.05)


def test_seeding_reproduces_and_distinguishes_rollouts() -> None:
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, size=(4, 2)).astype(np.float32)
    a_obs, a_rew = _rollout(_vec(2), seed=7, steps=30, actions=actions)
    b_obs, b_rew = _rollout(_vec(2), seed=7, steps=30, actions=actions)
    np.testing.assert_array_equal(a_obs, b_obs)
    np.testing.assert_array_equal(a_rew, b_rew)
    c_obs, _ = _rollout(_vec(2), seed=8, steps=30, actions=actions)
    assert not np.array_equal(a_obs, c_obs)
    # The two environments of one VecEnv draw different worlds (seed + i).
    venv = _vec(2)
    venv.seed(7)
    venv.reset()
    worlds = [e.par_env.world for e in venv.venv.vec_envs]
    assert worlds[0] != worlds[1]


def test_residual_env_with_zero_actions_runs_the_base_policy() -> None:
    """A zero network output means the base's own action: the randomized env then drives
    exactly like a ConvoyEnv in which every follower runs ``paper``."""
    r = Randomization(
        scenarios=("paper",),
        per_range=(0.3, 0.3),
        burst_prob=0.0,
        latency_s_range=(0.0, 0.0),
        jitter_s_range=(0.0, 0.0),
        gps_noise_m_range=(0.0, 0.0),
        vehicles=(),
        plant_jitter=0.0,
    )
    env = RandomizedConvoyEnv(EnvSpec(max_time_s=5.0), r)
    obs, _ = env.reset(seed=4)
    ref = ConvoyEnv(
        "paper", member_config=PRESETS["paper"].member, loss=LossConfig(per=0.3), max_time_s=5.0
    )
    # Same episode seed as the randomized env drew for its ConvoyEnv.
    rng = np.random.default_rng(4)
    draw_world(r, 2, rng)
    ref_obs, _ = ref.reset(seed=int(rng.integers(2**31 - 1)))
    policies = {a: load_policy("paper") for a in ref.possible_agents}
    while env.agents:
        np.testing.assert_array_equal(obs["follower_1"], ref_obs["follower_1"])
        obs, *_ = env.step({a: np.zeros(2, dtype=np.float32) for a in env.agents})
        ref_obs, *_ = ref.step({a: policies[a].act(o) for a, o in ref_obs.items()})
    assert env.env.t == pytest.approx(5.0)


def test_world_draws_stay_in_their_ranges(tmp_path) -> None:
    fitted = dataclasses.replace(VEHICLE_PRESETS["1/10"], name="fitted-car", speed_lag_s=0.5)
    path = tmp_path / "fitted.toml"
    path.write_text(preset_to_toml(fitted))
    r = Randomization(
        scenarios=("paper", "track"),
        per_range=(0.1, 0.5),
        burst_prob=0.5,
        latency_s_range=(0.02, 0.04),
        gps_noise_m_range=(0.0, 0.1),
        vehicles=(str(path),),
        plant_jitter=0.1,
    )
    rng = np.random.default_rng(0)
    worlds = [draw_world(r, 2, rng) for _ in range(200)]
    pers = np.array([w.loss.per for w in worlds])
    assert pers.min() >= 0.1 and pers.max() <= 0.5 and pers.std() > 0.05
    bursty = np.mean([w.loss.model == "gilbert-elliott" for w in worlds])
    assert 0.35 < bursty < 0.65
    assert all(0.02 <= w.loss.latency_s <= 0.04 for w in worlds)
    assert {w.scenario for w in worlds} == {"paper", "track"}
    lags = np.array([v.speed_lag_s for w in worlds for v in w.vehicles])
    assert lags.min() >= 0.5 * 0.9 - 1e-12 and lags.max() <= 0.5 * 1.1 + 1e-12
    assert all(v.name == "fitted-car" and len(w.vehicles) == 3 for w in worlds for v in w.vehicles)
    assert set(PLANT_JITTER_FIELDS) <= {f.name for f in dataclasses.fields(fitted)}
    # The fitted vehicles really drive the episode.
    env = RandomizedConvoyEnv(EnvSpec(max_time_s=0.5), r)
    env.reset(seed=0)
    assert [p.name for p in env.env.presets] == ["fitted-car"] * 3


def test_bad_randomization_is_refused_with_its_key() -> None:
    with pytest.raises(ValueError, match="per_range"):
        Randomization(per_range=(0.5, 0.2))
    with pytest.raises(ValueError, match="unknown vehicle preset 'bogus'"):
        Randomization(vehicles=("bogus",))
    with pytest.raises(ValueError, match="heading-change range"):
        EnvSpec(action_low=(0.0, -2.0))
