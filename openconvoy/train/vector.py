"""Parameter sharing on the batched simulator: an SB3 ``VecEnv`` over ``VectorConvoyEnv``.

Slot ``j`` is follower ``j % (N-1)`` of convoy ``j // (N-1)`` (the layout
``train.vec.SharedPolicyVecEnv`` uses), with no SuperSuit and no Python loop per agent in
the step. Convoys reset themselves when their episode ends (SB3's convention): the
returned observation is the new episode's, the last one is in
``infos[j]["terminal_observation"]``, and ``infos[j]["TimeLimit.truncated"]`` says
whether the episode was cut by the time limit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from openconvoy.envs.vector_env import VectorConvoyEnv


class VectorConvoyVecEnv(VecEnv):
    """``VectorConvoyEnv`` as an SB3 VecEnv with one slot per follower."""

    def __init__(self, env: VectorConvoyEnv) -> None:
        if not env.autoreset:
            raise ValueError("VectorConvoyVecEnv needs a VectorConvoyEnv with autoreset=True")
        self.env = env
        self.per_convoy = env.n_vehicles - 1
        obs_space = gymnasium.spaces.Box(
            -np.inf, np.inf, shape=(env.layout.size,), dtype=np.float32
        )
        low = env.action_low.min(axis=0).astype(np.float32)
        high = env.action_high.max(axis=0).astype(np.float32)
        act_space = gymnasium.spaces.Box(low=low, high=high, dtype=np.float32)
        super().__init__(env.num_envs * self.per_convoy, obs_space, act_space)
        self._actions: np.ndarray | None = None
        self._seed: int | None = None

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        """Seed the convoys at the next ``reset`` (convoy ``b`` gets ``seed + b``)."""
        self._seed = None if seed is None else int(seed)
        return [None] * self.num_envs

    def reset(self) -> np.ndarray:
        obs, _ = self.env.reset(seed=self._seed)
        self._seed = None
        return obs.reshape(self.num_envs, -1)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(
            self.env.num_envs, self.per_convoy, 2
        )

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        assert self._actions is not None, "step_async first"
        obs, rewards, term, trunc, info = self.env.step(self._actions)
        done = term | trunc
        per = self.per_convoy
        dones = np.repeat(done, per)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if done.any():
            final = info["final_observation"]
            for b in np.flatnonzero(done):  # episode ends only
                for j in range(per):
                    infos[b * per + j] = {
                        "terminal_observation": final[b, j],
                        "TimeLimit.truncated": bool(trunc[b]),
                    }
        return obs.reshape(self.num_envs, -1), rewards.reshape(-1).astype(np.float32), dones, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.env, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.env, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))
