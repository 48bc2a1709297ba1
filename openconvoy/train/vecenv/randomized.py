"""Domain randomization on the batched simulator: the training VecEnv of ``openconvoy train``.

``RandomizedVectorVecEnv`` runs ``n_convoys`` convoys as ``n_worlds`` groups, each a
``VectorConvoyEnv``: a group shares one draw of ``Randomization`` (scenario, vehicles
with their jittered autopilot response, burst model and length, latency), and every
convoy in it draws its own PER (``VectorConvoyEnv`` takes one PER per convoy). A group's
world lasts one episode length: then it is redrawn, and convoys that restarted within it
(after a collision) are cut there (``TimeLimit.truncated``), so the worlds keep changing
as ``RandomizedConvoyEnv``'s do at every episode. The groups' first worlds are cut short
by different amounts, so the groups run out of phase. Actions are normalized, composed with
the residual base (batched, each convoy's controller state its own) exactly as
``RandomizedConvoyEnv`` composes them (``policies.learned.compose_actions``).

``per_high`` (settable through ``VecEnv.set_attr``) caps the PERs of the next draws: a
curriculum raises it over training. ``batched_refusal`` says why a configuration cannot
run batched (traffic scenarios, until the batched simulator models them), so training
falls back to ``RandomizedConvoyEnv``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError, DependencyMissing
from openconvoy.envs.vector.env import VectorConvoyEnv
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.policies.batched import BatchedClassical
from openconvoy.policies.learned import compose_actions
from openconvoy.train.randomization import (
    EnvSpec,
    EpisodeWorld,
    Randomization,
    draw_world,
)
from openconvoy.train.vecenv.vector import VectorConvoyVecEnv


def draw_group(
    r: Randomization, n_followers: int, n_convoys: int, rng: np.random.Generator, per_high: float
) -> tuple[EpisodeWorld, list[float]]:
    """One group's world (``draw_world``; bursty with probability ``burst_prob``) and a
    PER per convoy, uniform in ``[per_range[0], max(per_range[0], per_high)]``."""
    world = draw_world(r, n_followers, rng)
    model = "gilbert-elliott" if rng.random() < r.burst_prob else "bernoulli"
    world = dataclasses.replace(world, loss=dataclasses.replace(world.loss, model=model))
    lo = r.per_range[0]
    pers = rng.uniform(lo, max(lo, min(per_high, r.per_range[1])), size=n_convoys)
    return world, [float(p) for p in pers]


def group_env(
    spec: EnvSpec, world: EpisodeWorld, pers: list[float], autoreset: bool = True
) -> VectorConvoyEnv:
    """The ``VectorConvoyEnv`` of one group: ``len(pers)`` convoys in ``world``."""
    return VectorConvoyEnv(
        len(pers),
        world.scenario,
        n_followers=None if world.vehicles is not None else spec.n_followers,
        member_config=spec.member_config,
        loss=[dataclasses.replace(world.loss, per=p) for p in pers],
        control_rate_hz=spec.rate_hz,
        gps_noise_m=world.gps_noise_m,
        max_time_s=spec.max_time_s,
        vehicle_presets=world.vehicles,
        reward_config=spec.reward,
        emergency_stop=bool(spec.emergency_stop),
        autoreset=autoreset,
    )


def batched_refusal(spec: EnvSpec, r: Randomization) -> str | None:
    """Why ``VectorConvoyEnv`` cannot run the worlds ``r`` draws (None: it can run them):
    it is asked for the widest draw of every scenario and vehicle preset."""
    if spec.reward_fn:
        return f"the reward plug-in {spec.reward_fn} runs in Python"
    if spec.obs_features:
        return f"the observation-features plug-in {spec.obs_features} runs in Python"
    if spec.plugin_base:
        return f"the plug-in residual base {spec.plugin_base} acts per follower"
    models = [
        m for m, p in (("bernoulli", r.burst_prob < 1), ("gilbert-elliott", r.burst_prob > 0)) if p
    ]
    for scenario in r.scenarios:
        for preset in r.vehicles or (None,):
            vehicles = (
                None if preset is None else (vehicle_preset(preset),) * (spec.n_followers + 1)
            )
            for model in models:
                loss = LossConfig(
                    per=r.per_range[1],
                    model=model,
                    mean_burst_s=r.mean_burst_s_range[1],
                    latency_s=r.latency_s_range[1],
                    jitter_s=r.jitter_s_range[1],
                )
                world = EpisodeWorld(scenario, loss, r.gps_noise_m_range[1], vehicles)
                try:
                    group_env(spec, world, [loss.per])
                except (ConfigError, DependencyMissing) as exc:
                    return str(exc)
    return None


class RandomizedVectorVecEnv(VectorConvoyVecEnv):
    """``n_convoys`` randomized convoys in ``n_worlds`` groups, normalized actions
    ``[-1, 1]^2`` (residual on ``spec``'s base when it has one), one slot per follower."""

    def __init__(
        self, spec: EnvSpec, randomization: Randomization, n_convoys: int, n_worlds: int = 4
    ) -> None:
        if n_convoys < 1:
            raise ConfigError(f"n_envs must be at least 1, got {n_convoys}")
        self.spec_ = spec
        self.randomization = randomization
        self.per_high = randomization.per_range[1]
        G = max(1, min(n_worlds, n_convoys))
        self._sizes = [n_convoys // G + (g < n_convoys % G) for g in range(G)]
        self._rng = np.random.default_rng()
        base = spec.base_config()
        self._bases = [BatchedClassical(base) for _ in range(G)] if base is not None else []
        self._age = [0] * G
        super().__init__([self._draw(g) for g in range(G)])

    def _action_space(self) -> gymnasium.spaces.Box:
        return gymnasium.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def _draw(self, g: int) -> VectorConvoyEnv:
        world, pers = draw_group(
            self.randomization, self.spec_.n_followers, self._sizes[g], self._rng, self.per_high
        )
        return group_env(self.spec_, world, pers)

    def _restart(self, g: int) -> np.ndarray:
        """Group ``g`` in a new world: its first observations."""
        self.envs[g] = self._draw(g)
        self._age[g] = 0
        if self._bases:
            self._bases[g].reset()
        obs, _ = self.envs[g].reset(seed=int(self._rng.integers(2**31 - 1)))
        return obs

    def reset(self) -> np.ndarray:
        if self._seed is not None:
            self._rng = np.random.default_rng(self._seed)
            self._seed = None
        self._obs = [self._restart(g) for g in range(len(self.envs))]
        # Stagger the groups: group g's first world is cut g/G of an episode early, so a
        # rollout holds every phase of the episode, not one phase of all of them.
        G = len(self.envs)
        for g, env in enumerate(self.envs):
            self._age[g] = (g * env.max_steps) // G
        return self._flat(self._obs)

    def _to_si(self, g: int, actions: np.ndarray) -> np.ndarray:
        s = self.spec_
        base = self._bases[g].act_batch(self._obs[g]) if self._bases else None
        return compose_actions(actions, *s.bounds, base, s.residual_scale)

    def _reward(
        self, g: int, rewards: np.ndarray, obs: np.ndarray, info: dict[str, Any]
    ) -> np.ndarray:
        extra = self.spec_.extra
        if not extra.active:
            return rewards
        # Convoys that restarted: the bonus is that of the tick that ended the episode.
        final = info.get("final_observation")
        after = obs if final is None else final
        layout = self.envs[g].layout
        return rewards + extra.bonus(layout, info["platooning_error_m"], after)

    def _after_step(self, g: int, done: np.ndarray) -> None:
        if self._bases and done.any():
            self._bases[g].reset_rows(np.repeat(done[:, None], self.per_convoy, axis=1))

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = super().step_wait()
        assert isinstance(obs, np.ndarray)
        start = 0
        for g, env in enumerate(self.envs):
            n = env.num_envs * self.per_convoy
            self._age[g] += 1
            if self._age[g] >= env.max_steps:
                # Convoys that restarted after a collision are cut where the world ends.
                for j in np.flatnonzero(~dones[start : start + n]) + start:
                    infos[j]["terminal_observation"] = obs[j].copy()
                    infos[j]["TimeLimit.truncated"] = True
                dones[start : start + n] = True
                self._obs[g] = self._restart(g)
                obs[start : start + n] = self._obs[g].reshape(n, -1)
            start += n
        return obs, rewards, dones, infos
