"""The simulator: plant, scenarios, channel, and the PettingZoo convoy environment.

``ConvoyEnv`` (PettingZoo parallel API; ``ConvoyEnv()`` is the ``paper`` scenario),
``convoy_aec_env`` (its AEC version), ``VectorConvoyEnv`` (many convoys batched, compiled kernels; the ``batched`` extra), and the single-agent Gymnasium view registered as
``OpenConvoy-v0`` (``openconvoy.envs.single_agent``).
"""

from openconvoy.envs.channel import Channel
from openconvoy.envs.convoy_env import INFO_KEYS, ConvoyEnv, convoy_aec_env
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.scenarios import SCENARIO_NAMES, Scenario, make_scenario
from openconvoy.envs.track import Track, load_track

__all__ = [
    "INFO_KEYS",
    "SCENARIO_NAMES",
    "HIGHWAY_SINGLE_AGENT_ID",
    "SINGLE_AGENT_ID",
    "Channel",
    "ConvoyEnv",
    "RewardConfig",
    "Scenario",
    "Track",
    "VectorConvoyEnv",
    "convoy_aec_env",
    "load_track",
    "make_scenario",
]

from typing import TYPE_CHECKING, Any

import gymnasium as _gymnasium

if TYPE_CHECKING:
    from openconvoy.envs.vector.env import VectorConvoyEnv


def __getattr__(name: str) -> Any:
    # VectorConvoyEnv needs numba (the ``batched`` extra): imported on first use, so the
    # rest of the simulator (and a vehicle's runtime) does not need it.
    if name == "VectorConvoyEnv":
        from openconvoy.envs.vector.env import VectorConvoyEnv

        return VectorConvoyEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


SINGLE_AGENT_ID = "OpenConvoy-v0"
"""Gymnasium id of the single-agent view (``openconvoy.envs.single_agent``)."""

if SINGLE_AGENT_ID not in _gymnasium.registry:
    _gymnasium.register(
        id=SINGLE_AGENT_ID, entry_point="openconvoy.envs.single_agent:SingleAgentConvoyEnv"
    )

HIGHWAY_SINGLE_AGENT_ID = "OpenConvoy-Highway-v0"
"""Gymnasium id of the single-agent view of ``highway-cut-in`` (the ``traffic`` extra): the
learner drives ``follower_1``, the other followers ``cacc-allpred+ladder``."""

if HIGHWAY_SINGLE_AGENT_ID not in _gymnasium.registry:
    _gymnasium.register(
        id=HIGHWAY_SINGLE_AGENT_ID,
        entry_point="openconvoy.envs.single_agent:SingleAgentConvoyEnv",
        kwargs={"scenario": "highway-cut-in", "others": "cacc-allpred+ladder"},
    )
