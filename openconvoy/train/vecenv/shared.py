"""Parameter sharing: every follower of every environment is one slot of one SB3 VecEnv.

A thin layer over SuperSuit (kept operational but no longer developed, so we depend on
as little of it as possible): ``pettingzoo_env_to_vec_env_v1`` turns one ParallelEnv into
a vector of its agents, ``concat_vec_envs_v1`` stacks ``n_envs`` copies in this process.
``SharedPolicyVecEnv`` fixes what SuperSuit's SB3 adapter leaves out: ``seed()`` (SB3
calls it at setup; the seed must reach the environments at the next ``reset``).

Slot ``j`` is agent ``j % n_agents`` of environment ``j // n_agents``. Environment ``i`` is
reset with seed ``seed + i``; afterwards each continues its own draw sequence.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import supersuit as ss
from pettingzoo import ParallelEnv
from stable_baselines3.common.vec_env import VecEnv
from supersuit.vector.sb3_vector_wrapper import SB3VecEnvWrapper

from openconvoy.core.errors import ConfigError


class SharedPolicyVecEnv(SB3VecEnvWrapper):
    """SuperSuit's SB3 adapter with working seeding (``seed`` then ``reset``)."""

    def __init__(self, venv) -> None:
        super().__init__(venv)
        self._pending_seed: int | None = None

    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seed the environments at the next ``reset`` (SB3's convention since gym 0.26)."""
        self._pending_seed = None if seed is None else int(seed)
        return [None] * self.num_envs

    def reset(self, seed: int | None = None, options=None) -> np.ndarray:
        if seed is not None:
            self._pending_seed = int(seed)
        seed, self._pending_seed = self._pending_seed, None
        observations, self.reset_infos = self.venv.reset(seed=seed)
        return observations

    def get_attr(self, attr_name: str, indices=None) -> list:
        """Only ``render_mode`` is answered (SB3 asks for it when wrapping)."""
        if attr_name == "render_mode":
            return [self.render_mode] * self.num_envs
        raise AttributeError(attr_name)

    def step_wait(self):
        observations, rewards, terminations, truncations, infos = self.venv.step_wait()
        dones = np.logical_or(terminations, truncations)
        for info, trunc, term in zip(infos, truncations, terminations):
            # SB3 bootstraps from the last observation on time limits only.
            info["TimeLimit.truncated"] = bool(trunc) and not bool(term)
        return observations, rewards, dones, infos


def shared_policy_vec_env(make_env: Callable[[], ParallelEnv], n_envs: int) -> VecEnv:
    """``n_envs`` copies of ``make_env()`` as one SB3 VecEnv with a slot per agent."""
    if n_envs < 1:
        raise ConfigError(f"n_envs must be at least 1, got {n_envs}")
    markov = ss.pettingzoo_env_to_vec_env_v1(make_env())
    # num_cpus=0: all copies in this process. On the small machines this targets, torch
    # already uses the cores; subprocesses would only add pickling overhead.
    stacked = ss.concat_vec_envs_v1(markov, n_envs, num_cpus=0, base_class="gymnasium")
    return SharedPolicyVecEnv(stacked)
