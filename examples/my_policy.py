"""A whole policy in 20 lines: keep the gap to the nearest predecessor, steer at its trail.

openconvoy sim --policy examples/my_policy.py:GapKeeper --policy-arg kp=0.5
"""

import math

import numpy as np

from openconvoy.core.observation import ObservationLayout


class GapKeeper:
    """Speed: the nearest predecessor's speed + kp × spacing error (m/s); heading: at the
    point 1 s ahead on its trail (rad). The platform clips, supervises and times it."""

    tunable = {"kp": (0.05, 2.0)}  # what `openconvoy tune` may search

    def __init__(self, kp: float = 0.4, max_speed_mps: float = 5.0) -> None:
        self.kp, self.max_speed_mps = kp, max_speed_mps
        self.layout = ObservationLayout()  # M = 2, k = 3: the default member's layout

    def act(self, observation: np.ndarray) -> np.ndarray:
        view = self.layout.view(observation)
        targets = view.valid_targets()  # nearest predecessor first
        if not targets:
            return np.zeros(2, dtype=np.float32)  # nobody heard: stand still
        near = targets[0]
        speed = near["speed"] + self.kp * near["spacing_error"]
        path = view.path
        heading = math.atan2(path["la1_y"], path["la1_x"]) if path["valid"] > 0.5 else 0.0
        return np.array([min(max(speed, 0.0), self.max_speed_mps), heading], dtype=np.float32)
