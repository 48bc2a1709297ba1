"""Parameter sharing on the batched simulator: an SB3 ``VecEnv`` over ``VectorConvoyEnv``.

Slot ``j`` is follower ``j % (N-1)`` of convoy ``j // (N-1)`` (the layout
``train.vecenv.shared.SharedPolicyVecEnv`` uses), with no SuperSuit and no Python loop per agent in
the step. Convoys reset themselves when their episode ends (SB3's convention): the
returned observation is the new episode's, the last one is in
``infos[j]["terminal_observation"]``, and ``infos[j]["TimeLimit.truncated"]`` says
whether the episode was cut by the time limit. Every slot's info also carries
``platooning_error_m`` (m) and ``collision``, as ``ConvoyEnv``'s do.

``VectorConvoyVecEnv`` may run several ``VectorConvoyEnv`` side by side (groups: convoys
that differ in more than their PER, e.g. in their vehicles); the convoys of group ``g``
follow those of the groups before it. ``RandomizedVectorVecEnv``
(``openconvoy.train.vecenv.randomized``) builds on it for training.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from openconvoy.envs.vector.env import VectorConvoyEnv


def _slot_infos(
    info: dict[str, Any], done: np.ndarray, trunc: np.ndarray, final: np.ndarray | None
) -> list[dict[str, Any]]:
    """Per-slot info dicts of one group's step (episode ends add the terminal facts)."""
    err = info["platooning_error_m"].reshape(-1).tolist()
    hit = info["collision"].reshape(-1).tolist()
    infos = [{"platooning_error_m": e, "collision": c} for e, c in zip(err, hit)]
    if final is not None and done.any():
        per = final.shape[1]
        for b in np.flatnonzero(done):  # episode ends only
            for j in range(per):
                infos[b * per + j]["terminal_observation"] = final[b, j]
                infos[b * per + j]["TimeLimit.truncated"] = bool(trunc[b])
    return infos


class VectorConvoyVecEnv(VecEnv):
    """``VectorConvoyEnv`` (or several, side by side) as an SB3 VecEnv with one slot per
    follower. Actions are the environment's: SI ``[speed_mps, heading_change_rad]``."""

    def __init__(self, env: VectorConvoyEnv | Sequence[VectorConvoyEnv]) -> None:
        self.envs = [env] if isinstance(env, VectorConvoyEnv) else list(env)
        first = self.envs[0]
        for e in self.envs:
            if not e.autoreset:
                raise ValueError("VectorConvoyVecEnv needs VectorConvoyEnvs with autoreset=True")
            if (e.n_vehicles, e.layout.size) != (first.n_vehicles, first.layout.size):
                raise ValueError("the groups must have the same convoy size and layout")
        self.per_convoy = first.n_vehicles - 1
        self.n_convoys = sum(e.num_envs for e in self.envs)
        obs_space = gymnasium.spaces.Box(
            -np.inf, np.inf, shape=(first.layout.size,), dtype=np.float32
        )
        self.render_mode = None
        super().__init__(self.n_convoys * self.per_convoy, obs_space, self._action_space())
        self._actions: np.ndarray | None = None
        self._seed: int | None = None
        self._obs: list[np.ndarray] = []

    @property
    def env(self) -> VectorConvoyEnv:
        """The first (with one group: the only) ``VectorConvoyEnv``."""
        return self.envs[0]

    def _action_space(self) -> gymnasium.spaces.Box:
        low = np.min([e.action_low.min(axis=0) for e in self.envs], axis=0).astype(np.float32)
        high = np.max([e.action_high.max(axis=0) for e in self.envs], axis=0).astype(np.float32)
        return gymnasium.spaces.Box(low=low, high=high, dtype=np.float32)

    def _offsets(self) -> list[int]:
        """The first convoy index of each group."""
        return [int(v) for v in np.cumsum([0] + [e.num_envs for e in self.envs])[:-1]]

    def _to_si(self, g: int, actions: np.ndarray) -> np.ndarray:
        """Group ``g``'s actions ``(B_g, N-1, 2)`` as the environment takes them."""
        return actions

    def _reward(
        self, g: int, rewards: np.ndarray, obs: np.ndarray, info: dict[str, Any]
    ) -> np.ndarray:
        """Group ``g``'s rewards ``(B_g, N-1)`` as the learner sees them (here: the
        environment's); ``obs`` the step's observations."""
        return rewards

    def _after_step(self, g: int, done: np.ndarray) -> None:
        """Called after group ``g`` stepped; ``done`` (B_g,) marks convoys that restarted."""

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        """Seed the convoys at the next ``reset`` (convoy ``b`` gets ``seed + b``)."""
        self._seed = None if seed is None else int(seed)
        return [None] * self.num_envs

    def reset(self) -> np.ndarray:
        seed, self._seed = self._seed, None
        self._obs = [
            e.reset(seed=None if seed is None else seed + o)[0]
            for e, o in zip(self.envs, self._offsets())
        ]
        return self._flat(self._obs)

    def _flat(self, parts: Sequence[np.ndarray]) -> np.ndarray:
        return np.concatenate([p.reshape(-1, p.shape[-1]) for p in parts])

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(
            self.n_convoys, self.per_convoy, 2
        )

    def step_wait(self) -> VecEnvStepReturn:
        assert self._actions is not None, "step_async first"
        rewards, dones, infos = [], [], []
        for g, (e, o) in enumerate(zip(self.envs, self._offsets())):
            a = self._to_si(g, self._actions[o : o + e.num_envs])
            obs, r, term, trunc, info = e.step(a)
            done = term | trunc
            self._obs[g] = obs
            self._after_step(g, done)
            rewards.append(self._reward(g, r, obs, info).reshape(-1))
            dones.append(np.repeat(done, self.per_convoy))
            infos += _slot_infos(info, done, trunc, info.get("final_observation"))
        return (
            self._flat(self._obs),
            np.concatenate(rewards).astype(np.float32),
            np.concatenate(dones),
            infos,
        )

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        result = getattr(self, method_name)(*method_args, **method_kwargs)
        return [result] * len(list(self._get_indices(indices)))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))
