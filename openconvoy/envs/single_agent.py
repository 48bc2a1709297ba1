"""The single-agent Gymnasium view: one learner drives one follower, policies drive the rest.

Registered as ``OpenConvoy-v0`` (``gymnasium.make("OpenConvoy-v0")``): the ``paper``
scenario, the learner driving ``follower_1``, every other follower running the ``paper``
policy. Observations, actions (SI units), rewards and infos are the learner's entries of
``ConvoyEnv``'s.

Import rule exception (DESIGN.md, Layout): ``envs`` does not import ``policies``. When
the other followers are given as a policy *spec string* (the default, ``"paper"``), this
module imports ``openconvoy.policies.spec`` lazily, inside the constructor, so that
``import openconvoy.envs`` stays free of it; pass a ``Policy`` instance or a factory to
avoid it altogether.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import gymnasium
import numpy as np

from openconvoy.core.member import MemberConfig
from openconvoy.core.policy import ConvoyPolicy, Policy, as_convoy_policy
from openconvoy.envs.convoy_env import ConvoyEnv
from openconvoy.envs.scenarios import Scenario

PolicySource = str | Policy | Callable[[], Policy]
"""A policy spec (``"paper"``, a TOML path, ...), an instance (deep-copied per follower,
since controllers keep state), or a zero-argument factory returning a fresh policy."""


def _factory(source: PolicySource) -> Callable[[], Policy]:
    if isinstance(source, str):
        from openconvoy.policies.spec import load_policy  # lazy: see the module docstring

        return lambda: load_policy(source)
    if isinstance(source, Policy):
        return lambda: copy.deepcopy(source)
    if callable(source):
        return source
    raise TypeError(
        f"others must be a policy spec, a Policy or a factory, got {type(source).__name__}"
    )


class SingleAgentConvoyEnv(gymnasium.Env):
    """``ConvoyEnv`` seen by one learner.

    Args:
        scenario: scenario spec or object (see ``ConvoyEnv``).
        others: what drives every follower but the learner (default ``"paper"``).
        agent: the learner's follower (``follower_1`` by default).
        member_config: the member configuration of all followers; default: the other
            policies' ``member_config`` (a ``ConvoyPolicy``; None: the scenario's), so
            the learner observes what they observe.
        control_rate_hz: default: the other policies' ``control_rate_hz``.
        render_mode: None or ``"rgb_array"``.
        **env_kwargs: passed to ``ConvoyEnv`` (``n_followers``, ``loss``, ``gps_noise_m``,
            ``max_time_s``, ``vehicle_presets``, ``reward_config``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        scenario: str | Scenario = "paper",
        others: PolicySource = "paper",
        agent: str = "follower_1",
        member_config: MemberConfig | None = None,
        control_rate_hz: float | None = None,
        render_mode: str | None = None,
        **env_kwargs: Any,
    ) -> None:
        make = _factory(others)
        probe: ConvoyPolicy = as_convoy_policy(make(), "others")
        if member_config is None:
            member_config = probe.member_config
        if control_rate_hz is None:
            control_rate_hz = float(probe.control_rate_hz)
        self.env = ConvoyEnv(
            scenario,
            member_config=member_config,
            control_rate_hz=control_rate_hz,
            render_mode=render_mode,
            **env_kwargs,
        )
        if agent not in self.env.possible_agents:
            raise ValueError(
                f"unknown agent {agent!r}; expected one of {', '.join(self.env.possible_agents)}"
            )
        self.agent = agent
        self.render_mode = render_mode
        others_agents = [a for a in self.env.possible_agents if a != agent]
        self.others: dict[str, Policy] = {}
        for i, a in enumerate(others_agents):
            self.others[a] = probe if i == 0 else make()
        self.observation_space = self.env.observation_space(agent)
        self.action_space = self.env.action_space(agent)
        self.metadata = {**self.metadata, "render_fps": int(round(self.env.control_rate_hz))}
        self._obs: dict[str, np.ndarray] = {}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._obs, infos = self.env.reset(seed=seed, options=options)
        for i, policy in enumerate(self.others.values()):
            policy.reset(None if seed is None else seed + i + 1)
        return self._obs[self.agent], infos[self.agent]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        actions = {a: p.act(self._obs[a]) for a, p in self.others.items()}
        actions[self.agent] = action
        self._obs, rewards, terms, truncs, infos = self.env.step(actions)
        a = self.agent
        return self._obs[a], rewards[a], terms[a], truncs[a], infos[a]

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()
