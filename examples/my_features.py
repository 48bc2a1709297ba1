"""Extra observation features for training: numbers computed from the observation and
appended to it (the trained policy records them and computes them wherever it runs).

    # train.toml
    [env]
    obs_features = "examples/my_features.py:GapRatio"
"""

import numpy as np

from openconvoy.core.observation import ObservationLayout


class GapRatio:
    """The immediate predecessor's arc gap over its desired gap (1 = on the spot) and its
    speed minus ours (m/s); zeros while it is unheard."""

    def __init__(self) -> None:
        self.layout = ObservationLayout()  # the default member's (M = 2, k = 3)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        view = self.layout.view(observation)
        pred = view.target("pred_1")
        if pred["valid"] < 0.5:
            return np.zeros(2, dtype=np.float32)
        ratio = pred["arc_gap"] / max(pred["desired_gap"], 1e-3)
        return np.array([ratio, pred["speed"] - view.own_speed], dtype=np.float32)
