"""The learner's reward: spacing error, comfort and collisions, per follower per tick.

``r = -w_spacing * min(|gap - desired_gap| / spacing_scale_m, 1)
      - w_accel * (accel / accel_scale_mps2)^2
      - w_jerk * (jerk / jerk_scale_mps3)^2
      - w_yaw_rate * (yaw_rate / yaw_rate_scale_radps)^2
      - collision_penalty * collided``

``gap`` is the ground-truth centre-to-centre distance to the immediate predecessor (the
metric's platooning error, DESIGN.md), ``desired_gap`` the member's spacing policy at that
instant; ``jerk`` is the change of the plant's acceleration over one tick. The spacing term
saturates so a learner far from its place still gets a bounded signal; a collision (gap
below the sum of the half lengths) costs ``collision_penalty`` once and ends the episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RewardConfig:
    """Weights and scales of the reward (SI units)."""

    w_spacing: float = 1.0
    spacing_scale_m: float = 5.0
    w_accel: float = 0.05
    accel_scale_mps2: float = 1.0
    w_jerk: float = 0.01
    jerk_scale_mps3: float = 5.0
    w_yaw_rate: float = 0.02
    yaw_rate_scale_radps: float = 0.785
    collision_penalty: float = 100.0

    def __post_init__(self) -> None:
        for name in ("spacing_scale_m", "accel_scale_mps2", "jerk_scale_mps3", "yaw_rate_scale_radps"):
            if getattr(self, name) <= 0:
                raise ValueError(f"reward {name} must be positive")


def reward(
    config: RewardConfig,
    platooning_error_m: np.ndarray,
    accel_mps2: np.ndarray,
    jerk_mps3: np.ndarray,
    yaw_rate_radps: np.ndarray,
    collided: np.ndarray,
) -> np.ndarray:
    """Rewards for arrays of followers (all arguments shaped alike); NaN errors count as 0."""
    c = config
    err = np.nan_to_num(np.minimum(np.abs(platooning_error_m) / c.spacing_scale_m, 1.0))
    return -(
        c.w_spacing * err
        + c.w_accel * (accel_mps2 / c.accel_scale_mps2) ** 2
        + c.w_jerk * (jerk_mps3 / c.jerk_scale_mps3) ** 2
        + c.w_yaw_rate * (yaw_rate_radps / c.yaw_rate_scale_radps) ** 2
        + c.collision_penalty * collided
    )
