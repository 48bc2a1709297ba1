"""``VectorConvoyEnv`` as a ``gymnasium.vector.VectorEnv``: one sub-environment per follower.

Parameter sharing, as ``train.vecenv.vector.VectorConvoyVecEnv`` for SB3: sub-environment ``j``
is follower ``j % (N-1)`` of convoy ``j // (N-1)``; ``single_observation_space`` is the
layout's ``Box(D)``, ``single_action_space`` ``Box(2)`` (SI: speed m/s, heading change
rad; the widest followers' bounds, each vehicle clips to its own). Autoreset mode
``SAME_STEP``: a finished convoy's followers return the next episode's first observation,
and ``infos["final_obs"]`` / ``infos["_final_obs"]`` carry the last one (Gymnasium's
layout for that mode).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from openconvoy.envs.vector.env import VectorConvoyEnv


class ConvoyVectorEnv(VectorEnv):
    """Gymnasium's vector API over a ``VectorConvoyEnv`` (made with ``autoreset=True``)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, env: VectorConvoyEnv) -> None:
        if not env.autoreset:
            raise ValueError("ConvoyVectorEnv needs a VectorConvoyEnv with autoreset=True")
        self.env = env
        self.per_convoy = env.n_vehicles - 1
        self.num_envs = env.num_envs * self.per_convoy
        self.single_observation_space = env.single_observation_space
        self.single_action_space = env.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset every convoy (convoy ``b`` seeded ``seed + b``)."""
        if seed is not None:
            self.action_space.seed(seed)
        obs, _ = self.env.reset(seed=seed)
        return obs.reshape(self.num_envs, -1), {}

    def step(self, actions: np.ndarray):
        a = np.asarray(actions, dtype=np.float32).reshape(self.env.num_envs, self.per_convoy, 2)
        obs, rewards, term, trunc, info = self.env.step(a)
        per = self.per_convoy
        infos: dict[str, Any] = {}
        done = term | trunc
        if done.any():
            mask = np.repeat(done, per)
            infos["final_obs"] = np.where(
                mask[:, None], info["final_observation"].reshape(self.num_envs, -1), 0.0
            )
            infos["_final_obs"] = mask
        return (
            obs.reshape(self.num_envs, -1),
            rewards.reshape(-1),
            np.repeat(term, per),
            np.repeat(trunc, per),
            infos,
        )

    def close_extras(self, **kwargs: Any) -> None:
        pass
