"""The simulator: plant, scenarios, channel, and the PettingZoo convoy environment.

``ConvoyEnv`` (PettingZoo parallel API; ``ConvoyEnv()`` is the ``paper`` scenario),
``convoy_aec_env`` (its AEC version), and the single-agent Gymnasium view registered as
``OpenConvoy-v0`` (``openconvoy.envs.single_agent``).
"""

from openconvoy.envs.convoy_env import ConvoyEnv, convoy_aec_env

__all__ = ["SINGLE_AGENT_ID", "ConvoyEnv", "convoy_aec_env"]

import gymnasium as _gymnasium

SINGLE_AGENT_ID = "OpenConvoy-v0"
"""Gymnasium id of the single-agent view (``openconvoy.envs.single_agent``)."""

if SINGLE_AGENT_ID not in _gymnasium.registry:
    _gymnasium.register(
        id=SINGLE_AGENT_ID, entry_point="openconvoy.envs.single_agent:SingleAgentConvoyEnv"
    )
