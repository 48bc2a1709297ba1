"""A training reward: the environment's, minus a penalty on hard acceleration.

# train.toml
[env]
reward_fn = "examples/my_reward.py:Smooth?weight=0.2"
"""


class Smooth:
    """Called per follower per step: ``(reward, info, observation) -> float``; ``info``
    holds the follower's ``accel_mps2`` (m/s²), ``platooning_error_m`` (m) and the rest
    of ``ConvoyEnv.INFO_KEYS``."""

    def __init__(self, weight: float = 0.1) -> None:
        self.weight = weight

    def __call__(self, reward: float, info: dict, observation) -> float:
        return reward - self.weight * abs(info["accel_mps2"])
