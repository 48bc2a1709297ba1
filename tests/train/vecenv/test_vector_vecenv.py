"""The SB3 VecEnvs over VectorConvoyEnv: shapes, autoreset, PPO runs on them; the
randomized training env (residual base, worlds, curriculum cap), the fallback to
SuperSuit, and batched validation equal to run-by-run validation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecCheckNan, VecNormalize

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError
from openconvoy.envs import VectorConvoyEnv
from openconvoy.policies import load_policy
from openconvoy.policies.presets import PRESETS
from openconvoy.train.config import TrainConfig
from openconvoy.train.randomization import TRAIN_REWARD, EnvSpec, Randomization
from openconvoy.train.shaping import Shaping
from openconvoy.train.train import simulator_vec_env
from openconvoy.train.validate import validate
from openconvoy.train.vecenv.randomized import RandomizedVectorVecEnv, draw_group
from openconvoy.train.vecenv.shared import SharedPolicyVecEnv
from openconvoy.train.vecenv.vector import VectorConvoyVecEnv


def test_slots_are_followers_and_episodes_restart() -> None:
    venv = VectorConvoyVecEnv(VectorConvoyEnv(4, "paper", max_time_s=0.5))
    assert venv.num_envs == 8
    venv.seed(3)
    obs = venv.reset()
    assert obs.shape == (8, venv.observation_space.shape[0]) and obs.dtype == np.float32
    actions = np.tile(np.array([1.0, 0.0], np.float32), (8, 1))
    for k in range(10):
        venv.step_async(actions)
        obs, rewards, dones, infos = venv.step_wait()
        assert rewards.shape == (8,) and dones.shape == (8,)
        if k < 9:
            assert not dones.any()
    assert dones.all()
    assert all(i["TimeLimit.truncated"] for i in infos)
    assert infos[0]["terminal_observation"].shape == obs.shape[1:]
    # The restarted convoys begin where a fresh reset does.
    fresh = VectorConvoyVecEnv(VectorConvoyEnv(4, "paper", max_time_s=0.5))
    fresh.seed(3)
    np.testing.assert_array_equal(obs, fresh.reset())


def test_ppo_trains_on_it_without_nans() -> None:
    venv = VecNormalize(
        VecCheckNan(
            VectorConvoyVecEnv(VectorConvoyEnv(8, "paper", max_time_s=5.0)), raise_exception=True
        )
    )
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=128, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=2 * 32 * venv.num_envs)
    assert model.num_timesteps >= 2 * 32 * venv.num_envs


FIXED = Randomization(
    per_range=(0.3, 0.3),
    burst_prob=0.0,
    latency_s_range=(0.0, 0.0),
    vehicles=(),
    plant_jitter=0.0,
)
"""One world: the paper scenario's own vehicles at PER 0.3, Bernoulli, no latency."""


def test_zero_residual_drives_like_the_base_and_worlds_last_one_episode() -> None:
    """Batched training env, zero network output: every convoy is a VectorConvoyEnv convoy
    driven by ``paper``; after one episode length the world is redrawn and every slot
    restarts, with its terminal observation."""
    # No shaping bonus: the rewards are the simulator's (test_shaping checks the bonus).
    spec = EnvSpec(max_time_s=1.0, shaping=Shaping())
    venv = RandomizedVectorVecEnv(spec, FIXED, n_convoys=3, n_worlds=1)
    assert venv.num_envs == 6 and venv.action_space.shape == (2,)
    venv.seed(5)
    obs = venv.reset()
    rng = np.random.default_rng(5)
    draw_group(FIXED, 2, 3, rng, 0.3)
    ref = VectorConvoyEnv(
        3,
        "paper",
        member_config=PRESETS["paper"].member,
        loss=LossConfig(per=0.3),
        max_time_s=1.0,
        reward_config=TRAIN_REWARD,
    )
    ref_obs, _ = ref.reset(seed=int(rng.integers(2**31 - 1)))
    driver = load_policy("paper")
    zero = np.zeros((6, 2), np.float32)
    for k in range(ref.max_steps):
        np.testing.assert_array_equal(obs, ref_obs.reshape(6, -1))
        assert venv.observation_space.contains(obs[0])
        obs, rewards, dones, infos = venv.step(zero)
        ref_obs, ref_rewards, *_ = ref.step(driver.act_batch(ref_obs))
        np.testing.assert_array_equal(rewards, ref_rewards.reshape(-1).astype(np.float32))
        assert dones.all() == (k == ref.max_steps - 1) and math.isfinite(
            infos[0]["platooning_error_m"]
        )
    assert all(i["TimeLimit.truncated"] and "terminal_observation" in i for i in infos)
    assert not np.array_equal(obs, ref_obs.reshape(6, -1))  # a new world, new seeds


def test_groups_draw_their_own_worlds_and_convoys_their_own_per() -> None:
    r = Randomization(per_range=(0.0, 0.6), plant_jitter=0.2, latency_s_range=(0.0, 0.05))
    venv = RandomizedVectorVecEnv(EnvSpec(max_time_s=1.0), r, n_convoys=7, n_worlds=2)
    venv.seed(0)
    venv.reset()
    assert [e.num_envs for e in venv.envs] == [4, 3] and venv.num_envs == 14
    assert venv.envs[0].presets != venv.envs[1].presets
    pers = [c.per for e in venv.envs for c in e.losses]
    assert len(set(pers)) == 7 and 0.0 <= min(pers) and max(pers) <= 0.6
    # The groups run out of phase: the second one's first world lasts half an episode.
    for _ in range(10):
        _, _, dones, _ = venv.step(np.zeros((14, 2), np.float32))
    assert not dones[:8].any() and dones[8:].all()
    # A curriculum caps the PERs of the next draws.
    venv.set_attr("per_high", 0.1)
    venv.reset()
    assert max(c.per for e in venv.envs for c in e.losses) <= 0.1


def test_auto_falls_back_to_supersuit_with_one_line(capsys: pytest.CaptureFixture) -> None:
    traffic = TrainConfig(n_envs=2, randomization=Randomization(scenarios=("highway-cut-in",)))
    venv = simulator_vec_env(traffic)
    assert isinstance(venv, SharedPolicyVecEnv) and venv.num_envs == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "path scenarios" in err[0] and "SuperSuit" in err[0]
    with pytest.raises(ConfigError, match="path scenarios"):
        simulator_vec_env(dataclasses.replace(traffic, vec_env="batched"))
    # GPS noise and latency jitter run batched now.
    noisy = Randomization(gps_noise_m_range=(0.0, 0.05), jitter_s_range=(0.0, 0.05))
    assert isinstance(simulator_vec_env(TrainConfig(n_envs=2, randomization=noisy)),
                      RandomizedVectorVecEnv)  # fmt: skip
    assert isinstance(simulator_vec_env(TrainConfig(n_envs=2)), RandomizedVectorVecEnv)
    assert capsys.readouterr().err == ""


def test_batched_validation_equals_run_by_run() -> None:
    """The validation's batched runs give ``run_sim``'s metrics, digit for digit."""
    args = ("paper", (0.0, 0.6), (1000, 1001))
    batched = validate(*args, duration_s=4.0)
    single = validate(*args, duration_s=4.0, batched=False)
    assert batched.metrics == single.metrics and batched.objective == single.objective
    assert len(batched.metrics) == 4 and batched.metrics[0]["p95_platooning_error_m"] > 0
