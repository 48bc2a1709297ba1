"""The SB3 VecEnv over VectorConvoyEnv: shapes, autoreset, and PPO runs on it."""

from __future__ import annotations

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecCheckNan, VecNormalize

from openconvoy.envs import VectorConvoyEnv
from openconvoy.train.vector import VectorConvoyVecEnv


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
