"""The Policy protocol: the one interface classical and learned controllers share.

A policy maps an observation (``ObservationLayout`` array) to an action
``[speed_mps, heading_change_rad]`` in SI units: the speed setpoint and the heading
setpoint as an offset from the current heading, within ±π/2. It cannot tell the simulator
from a vehicle.
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

MAX_HEADING_CHANGE_RAD = math.pi / 2


@runtime_checkable
class Policy(Protocol):
    def reset(self, seed: int | None = None) -> None:
        """Forget internal state (controller memories) before a new run."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The action for one observation: ``[speed_mps, heading_change_rad]``."""


def make_action(speed_mps: float, heading_change_rad: float) -> np.ndarray:
    """An action array with the heading change clipped to ±π/2."""
    h = min(max(heading_change_rad, -MAX_HEADING_CHANGE_RAD), MAX_HEADING_CHANGE_RAD)
    return np.array([speed_mps, h], dtype=np.float32)
