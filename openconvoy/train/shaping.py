"""The training environments' term on top of the simulator's reward (``envs.reward``).

``bonus = weight * f(e, gap_scale_m) * f(cross_track, path_scale_m)
                 * f(heading_error, heading_scale_rad)``,  ``f(x, s) = 1 - min(|x| / s, 1)``

per follower per tick, added to the reward by both training paths
(``RandomizedConvoyEnv``, ``RandomizedVectorVecEnv``). ``e`` is the platooning error (m,
the metric's: Euclidean gap minus desired gap); ``cross_track`` the observation's offset
from the nearest heard predecessor's trail (m) and ``heading_error`` the angle between
that trail and the follower's heading (rad), both 0 where the observation holds no trail.

Why: the 30 m spacing term of ``SCRATCH_REWARD`` keeps a follower far behind pulled
back, but barely tells the last metre, where the metrics are decided, from the next;
the bonus pays for being within ``gap_scale_m`` of the desired gap. And the metric's gap is
a straight-line distance, blind to where a follower is beside its predecessor: learning
from scratch, a policy paid only for that gap kept it within 1 m while drifting off the
road, 15-30 m sideways by the end of an episode (a circle around the predecessor has the
right gap everywhere). So the bonus pays only on the predecessor's trail, heading along
it, as the paper's Stanley controller drives (an additive trail term saturating at 1 m
still let the followers drift 4-5 m). The factors multiply, so the trail pays only in
place, not a follower sitting far behind on the road. A bonus, not a penalty: with every
tick's reward negative, ending the episode in a collision (its penalty once) can be worth
more than driving on from far behind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np

from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError
from openconvoy.core.observation import PATH_FEATURES, ObservationLayout


@dataclass(frozen=True)
class Shaping:
    """The bonus's weight and scales (m, rad; ``inf``: that factor is 1); weight 0: none."""

    weight: Annotated[float, Range(0.0, 1e6)] = 0.0
    gap_scale_m: Annotated[float, Range(0.0, None, lo_open=True, allow_inf=True)] = 1.0
    path_scale_m: Annotated[float, Range(0.0, None, lo_open=True, allow_inf=True)] = math.inf
    heading_scale_rad: Annotated[float, Range(0.0, None, lo_open=True, allow_inf=True)] = math.inf

    def __post_init__(self) -> None:
        if self.weight < 0:
            raise ConfigError("shaping.weight must be >= 0")
        if min(self.gap_scale_m, self.path_scale_m, self.heading_scale_rad) <= 0:
            raise ConfigError("shaping scales must be positive")

    @property
    def active(self) -> bool:
        return self.weight > 0

    def bonus(self, layout: ObservationLayout, error_m: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The bonus of each follower: ``error_m`` (...,) platooning errors (NaN: none,
        counted as 0 like the simulator's spacing term), ``obs`` (..., layout.size) the
        observations after the tick."""
        e = np.nan_to_num(np.abs(np.asarray(error_m, dtype=float)), nan=0.0)
        out = self.weight * _factor(e, self.gap_scale_m)
        out = out * _factor(_trail_feature(layout, obs, "cross_track"), self.path_scale_m)
        return out * _factor(_trail_feature(layout, obs, "heading_error"), self.heading_scale_rad)


def _factor(x: np.ndarray, scale: float) -> np.ndarray:
    return 1.0 - np.minimum(x / scale, 1.0)


def _trail_feature(layout: ObservationLayout, obs: np.ndarray, feature: str) -> np.ndarray:
    """``|feature|`` of the observations' path features, 0 where no trail is heard."""
    o = layout.path_offset
    valid = obs[..., o + PATH_FEATURES.index("valid")] > 0.5
    value = np.abs(obs[..., o + PATH_FEATURES.index(feature)].astype(float))
    return np.where(valid, np.nan_to_num(value, nan=0.0), 0.0)
