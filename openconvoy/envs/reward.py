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

from collections.abc import Sequence
from dataclasses import dataclass

from openconvoy.core.errors import ConfigError


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
        for name in (
            "spacing_scale_m",
            "accel_scale_mps2",
            "jerk_scale_mps3",
            "yaw_rate_scale_radps",
        ):
            if getattr(self, name) <= 0:
                raise ConfigError(f"reward {name} must be positive")


def reward(
    config: RewardConfig,
    platooning_error_m: Sequence[float],
    accel_mps2: Sequence[float],
    jerk_mps3: Sequence[float],
    yaw_rate_radps: Sequence[float],
    collided: Sequence[bool],
) -> list[float]:
    """Rewards for sequences of followers (all alike in length); NaN errors count as 0.

    Plain Python floats: for convoys of a few vehicles this is several times cheaper than
    numpy on tiny arrays, and it runs every tick.
    """
    c = config
    out = []
    for e, a, j, w, hit in zip(platooning_error_m, accel_mps2, jerk_mps3, yaw_rate_radps, collided):
        e = abs(e) / c.spacing_scale_m
        e = 0.0 if e != e else min(e, 1.0)  # NaN -> 0
        a /= c.accel_scale_mps2
        j /= c.jerk_scale_mps3
        w /= c.yaw_rate_scale_radps
        out.append(
            -(
                c.w_spacing * e
                + c.w_accel * a * a
                + c.w_jerk * j * j
                + c.w_yaw_rate * w * w
                + (c.collision_penalty if hit else 0.0)
            )
        )
    return out
