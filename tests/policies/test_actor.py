"""``openconvoy.policies.actor``: the numpy actor taken out of an SB3 model is SB3's
deterministic ``predict``, for each head SB3 builds (PPO, PPO with gSDE and a squashed
output, SAC, SAC with gSDE's clipped mean), and the mean clip survives an export."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the train extra is not installed")

from stable_baselines3 import PPO, SAC  # noqa: E402

from openconvoy.policies.actor import actor_mlp  # noqa: E402
from openconvoy.policies.learned import NumpyMLP, load_npz, save_npz  # noqa: E402
from openconvoy.policies.presets import PRESETS  # noqa: E402


class Box(gym.Env):
    """Flat observations in a wide range (so clips are reached), 2-D actions in [-1, 1]."""

    observation_space = gym.spaces.Box(-50.0, 50.0, shape=(6,), dtype=np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def reset(self, seed=None, options=None):
        return np.zeros(6, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(6, dtype=np.float32), 0.0, True, False, {}


MODELS = {
    "ppo": lambda: PPO("MlpPolicy", Box(), seed=1, device="cpu"),
    "ppo-gsde-squashed": lambda: PPO(
        "MlpPolicy", Box(), use_sde=True, seed=1, device="cpu",
        policy_kwargs={"squash_output": True, "activation_fn": __import__("torch").nn.ReLU},
    ),
    "sac": lambda: SAC("MlpPolicy", Box(), seed=1, device="cpu"),
    "sac-gsde": lambda: SAC("MlpPolicy", Box(), use_sde=True, seed=1, device="cpu"),
}  # fmt: skip


def _worst(mlp: NumpyMLP, model, observations: np.ndarray) -> float:
    return max(
        float(np.max(np.abs(mlp(o) - model.predict(o, deterministic=True)[0])))
        for o in observations
    )


@pytest.mark.parametrize("kind", list(MODELS))
def test_the_numpy_actor_is_sb3s_predict(kind: str) -> None:
    model = MODELS[kind]()
    rng = np.random.default_rng(0)
    obs = rng.normal(scale=20.0, size=(100, 6)).astype(np.float32)
    mlp = actor_mlp(model)
    assert _worst(mlp, model, obs) <= 1e-5
    assert np.ptp([mlp(o)[0] for o in obs]) > 1e-3  # not a constant
    assert mlp.mean_clip == (2.0 if kind == "sac-gsde" else 0.0)


def test_the_sac_gsde_mean_clip_is_reached_and_survives_an_export(tmp_path: Path) -> None:
    """With the weights scaled up the mean passes ±2: only the clip keeps the numpy actor
    on SB3's action, and the .npz keeps the clip."""
    import torch

    model = MODELS["sac-gsde"]()
    with torch.no_grad():
        for p in model.policy.actor.mu[0].parameters():
            p.mul_(50.0)
    obs = np.random.default_rng(1).normal(scale=20.0, size=(100, 6)).astype(np.float32)
    mlp = actor_mlp(model)
    unclipped = NumpyMLP(mlp.weights, mlp.biases, mlp.activation, mlp.output)
    assert _worst(mlp, model, obs) <= 1e-5 and _worst(unclipped, model, obs) > 1e-2
    member = PRESETS["paper"].member
    size = member.layout.size
    big = NumpyMLP(
        [np.ones((4, size)), np.ones((2, 4))], [np.zeros(4), np.zeros(2)], "relu", "tanh", 2.0
    )
    from openconvoy.policies.learned import LearnedMeta

    meta = LearnedMeta("sac", member.layout.describe(), member, 20.0, (0.0, -0.5), (5.0, 0.5))
    _, loaded = load_npz(save_npz(tmp_path / "p.npz", meta, big))
    assert loaded.mean_clip == 2.0
    assert loaded(np.ones(size))[0] == pytest.approx(np.tanh(2.0))
