"""The simulator: plant, scenarios, channel, and the PettingZoo convoy environment.

``ConvoyEnv`` (PettingZoo parallel API; ``ConvoyEnv()`` is the ``paper`` scenario),
``convoy_aec_env`` (its AEC version), and the single-agent Gymnasium view registered as
``OpenConvoy-v0`` (``openconvoy.envs.single_agent``).
"""

from openconvoy.envs.convoy_env import ConvoyEnv, convoy_aec_env

__all__ = ["ConvoyEnv", "convoy_aec_env"]
