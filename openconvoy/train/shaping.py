"""The training environments' terms on top of the simulator's reward (``envs.reward``).

``bonus = w_precision * (1 - min(|e| / precision_scale_m, 1))
        + w_path * (1 - min(|cross_track| / path_scale_m, 1))``

per follower per tick, added to the reward by both training paths
(``RandomizedConvoyEnv``, ``RandomizedVectorVecEnv``). ``e`` is the platooning error (m,
the metric's: Euclidean gap minus desired gap); ``cross_track`` is the observation's
offset from the nearest heard predecessor's trail (m; 0 where the observation holds no
trail). Why: the metric's gap is a straight-line distance, blind to where a follower is
beside its predecessor. Learning from scratch, a policy paid only for that gap kept it
to 1 m while drifting off the road, 15-30 m sideways by the end of an episode (a circle
of 15 m around the predecessor has the right gap everywhere); the path term keeps it on
the predecessor's trail, as the paper's Stanley controller does. The precision term pays
for the last metre of the gap, where the metrics are decided, which the 30 m spacing
term of ``SCRATCH_REWARD`` barely distinguishes. The terms are bonuses, not penalties
(0 at their scale and beyond): with every tick's reward negative, ending the episode in a
collision (its penalty once) was worth more than the discounted penalties of driving on
from far behind, and the learner found it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError
from openconvoy.core.observation import PATH_FEATURES, ObservationLayout


@dataclass(frozen=True)
class Shaping:
    """The extra terms' weights and scales (m); all-zero weights: the simulator's reward."""

    w_precision: Annotated[float, Range(0.0, 1e6)] = 0.0
    precision_scale_m: Annotated[float, Range(0.0, 1e6, lo_open=True)] = 1.0
    w_path: Annotated[float, Range(0.0, 1e6)] = 0.0
    path_scale_m: Annotated[float, Range(0.0, 1e6, lo_open=True)] = 1.0

    def __post_init__(self) -> None:
        if min(self.w_precision, self.w_path) < 0:
            raise ConfigError("shaping weights must be >= 0")
        if min(self.precision_scale_m, self.path_scale_m) <= 0:
            raise ConfigError("shaping scales must be positive")

    @property
    def active(self) -> bool:
        return bool(self.w_precision or self.w_path)

    def bonus(self, layout: ObservationLayout, error_m: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The bonus of each follower: ``error_m`` (...,) platooning errors (NaN: none,
        counted as 0 like the simulator's spacing term), ``obs`` (..., layout.size) the
        observations after the tick (no trail heard: cross-track 0)."""
        e = np.nan_to_num(np.abs(np.asarray(error_m, dtype=float)), nan=0.0)
        out = self.w_precision * (1.0 - np.minimum(e / self.precision_scale_m, 1.0))
        if self.w_path:
            o = layout.path_offset
            valid = obs[..., o + PATH_FEATURES.index("valid")] > 0.5
            xt = np.abs(obs[..., o + PATH_FEATURES.index("cross_track")].astype(float))
            xt = np.where(valid, np.nan_to_num(xt, nan=0.0), 0.0)
            out = out + self.w_path * (1.0 - np.minimum(xt / self.path_scale_m, 1.0))
        return out
