"""Ranging sensors of the batched simulator: each follower's forward rangefinder reading.

``ConvoyWorld.ranging_readings`` for every convoy at once: the range (m, centre to centre)
and range rate (m/s, negative = closing) from each follower with a sensor to the vehicle
ahead, from the plant's true state (``core.ranging.range_and_rate``), when within the
sensor's range, plus its noise (``envs.ranging_noise``: the same counter-based draws, keyed
by the convoy's ranging key, the vehicle and the tick). The member's ``decide`` takes the
reading (NaN range: none) into the ladder's ACC fallback, the ranging override and the
emergency rule.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openconvoy.core import ranging as core_ranging
from openconvoy.envs.ranging_noise import ranging_key
from openconvoy.envs.vector.gps import counter_normals
from openconvoy.envs.vector.jit import bare_kernel, rules
from openconvoy.envs.vector.plant import HEADING, SPEED, X, Y
from openconvoy.envs.vehicles import VehiclePreset

rules(core_ranging, "range_and_rate")
RANGE, RATE = range(2)
"""Rows of ``RangingSensors.reading``: range (m), range rate (m/s)."""
MAX_RANGE, RANGE_NOISE, RATE_NOISE = range(3)
"""Rows of ``RangingSensors.params``: max range (m; 0 = no sensor), range noise (m), rate
noise (m/s)."""


class RangingSensors:
    """The sensors of ``presets`` (leader first; the leader's unused) in ``B`` convoys.

    ``reading`` (2, B, N): the last ``read``'s range (m) and range rate (m/s) per vehicle,
    NaN range where there is none; ``any``: some follower has a sensor."""

    def __init__(self, presets: Sequence[VehiclePreset], B: int) -> None:
        N = len(presets)
        sensors = [p.ranging if i > 0 else None for i, p in enumerate(presets)]
        # Per vehicle: max range (m; 0 = no sensor), range noise (m), rate noise (m/s).
        self.params = np.array(
            [
                [s.max_range_m, s.range_noise_m, s.range_rate_noise_mps] if s else [0.0] * 3
                for s in sensors
            ]
        ).T.copy()
        self.any = any(s is not None for s in sensors)
        self.keys = np.zeros(B, dtype=np.uint64)
        self.reading = np.full((2, B, N), np.nan)

    def seed(self, b: int, seq: np.random.SeedSequence) -> None:
        """Convoy ``b``'s ranging key from its ranging seed sequence, as ``ConvoyWorld.reset``."""
        self.keys[b] = np.uint64(ranging_key(seq))

    def read(self, own: np.ndarray, step: np.ndarray) -> None:
        """The readings of the true state ``own`` (6, B, N) at tick ``step`` (B,)."""
        if self.any:
            _read(own, step, self.keys, self.params, self.reading)


@bare_kernel
def _read(own, step, keys, params, out):  # pragma: no cover - compiled
    """``out`` (2, B, N): every follower's reading (NaN range: no sensor, or nothing in
    range), as ``ConvoyWorld.ranging_readings``: ``core.ranging.range_and_rate`` compiled,
    with ``ranging_noise.ranging_normals``' draws (``counter_normals``)."""
    _, B, N = own.shape
    for b in range(B):
        for i in range(1, N):
            out[RANGE, b, i], out[RATE, b, i] = np.nan, np.nan
            max_range = params[MAX_RANGE, i]
            if max_range <= 0.0:  # no sensor
                continue
            rng_m, rate = core_ranging.range_and_rate(
                own[X, b, i], own[Y, b, i], own[SPEED, b, i], own[HEADING, b, i],
                own[X, b, i - 1], own[Y, b, i - 1], own[SPEED, b, i - 1], own[HEADING, b, i - 1],
            )  # fmt: skip
            if rng_m > max_range or rng_m <= 0.0:  # ConvoyWorld.ranging_readings' guard
                continue
            n_range, n_rate = counter_normals(keys[b], i, step[b])
            out[RANGE, b, i] = rng_m + params[RANGE_NOISE, i] * n_range
            out[RATE, b, i] = rate + params[RATE_NOISE, i] * n_rate
