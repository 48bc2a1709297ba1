"""Test plug-ins for the batched path: ``Batchable`` has an ``act_batch`` equal to its
``act`` to the bit; ``Inexact``'s differs (it rounds the speed), so sweeps refuse to batch it."""

import numpy as np

from openconvoy.core.observation import ObservationLayout


class Batchable:
    """Speed: nearest predecessor's speed + kp × spacing error; heading 0."""

    def __init__(self, kp: float = 0.4) -> None:
        self.kp = kp
        self.layout = ObservationLayout()

    def act(self, observation: np.ndarray) -> np.ndarray:
        return Batchable.act_batch(self, observation[None, :])[0]

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        o = self.layout.target_offset("pred_1")  # arc_gap, desired_gap, spacing_error, speed, valid
        error, speed, valid = (
            observations[..., o + 2],
            observations[..., o + 3],
            observations[..., o + 4],
        )
        v = np.where(valid > 0.5, np.clip(speed + np.float32(self.kp) * error, 0.0, 5.0), 0.0)
        return np.stack([v, np.zeros_like(v)], axis=-1).astype(np.float32)


class Inexact(Batchable):
    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        out = super().act_batch(observations)
        out[..., 0] = np.round(out[..., 0], 1)
        return out
