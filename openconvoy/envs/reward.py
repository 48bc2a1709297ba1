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

    @property
    def numbers(self) -> tuple[float, ...]:
        """The scales then the weights, as ``follower_reward`` reads them: spacing, accel,
        jerk and yaw-rate scales, the four weights in that order, the collision penalty."""
        return (
            self.spacing_scale_m,
            self.accel_scale_mps2,
            self.jerk_scale_mps3,
            self.yaw_rate_scale_radps,
            self.w_spacing,
            self.w_accel,
            self.w_jerk,
            self.w_yaw_rate,
            self.collision_penalty,
        )

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
    c = config.numbers
    return [
        follower_reward(c, e, a, j, w, hit)
        for e, a, j, w, hit in zip(
            platooning_error_m, accel_mps2, jerk_mps3, yaw_rate_radps, collided
        )
    ]


def follower_reward(
    c: Sequence[float], error_m: float, accel: float, jerk: float, yaw_rate: float, hit: bool
) -> float:
    """One follower's reward: ``c`` is ``RewardConfig.numbers``; the platooning error (m;
    NaN counts as 0), acceleration (m/s²), jerk (m/s³), yaw rate (rad/s), and whether it
    collided. The batched kernels call this function compiled (``envs.vector.jit.rules``)."""
    e = abs(error_m) / c[0]
    e = 0.0 if e != e else min(e, 1.0)  # NaN -> 0
    a = accel / c[1]
    j = jerk / c[2]
    w = yaw_rate / c[3]
    pen = c[8] if hit else 0.0
    return -(c[4] * e + c[5] * a * a + c[6] * j * j + c[7] * w * w + pen)
