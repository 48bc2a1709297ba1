"""Simulated ranging-sensor noise, drawn counter-based (as ``envs.gps`` draws GPS noise).

A follower's forward rangefinder reading at tick ``k`` is off by ``range_noise_m * z_1`` in
range and ``range_rate_noise_mps * z_2`` in range rate: two independent standard normals
from one Box-Muller pair of counter-based uniforms (``comms.loss.counter_uniform(key,
vehicle, k, j)``, ``j = 0, 1``) under the episode's ranging key. The draws depend only on
(key, vehicle, tick), not on which other sensors see a target at that tick, so the batched
simulator (``envs.vector.ranging``) makes the same ones in a compiled kernel.
"""

from __future__ import annotations

import numpy as np

from openconvoy.comms.loss import counter_state, counter_uniform_from
from openconvoy.envs.gps import box_muller, gps_key


def ranging_key(seq: np.random.SeedSequence) -> int:
    """An episode's ranging key, drawn from a fresh generator of its ranging seed sequence
    (the traffic world draws its noise from another one, unchanged)."""
    return gps_key(np.random.default_rng(seq))


def ranging_normals(vehicle_state: int, tick: int) -> tuple[float, float]:
    """The two standard normals (range, range rate) of a vehicle's reading at ``tick``;
    ``vehicle_state`` is ``comms.loss.counter_state(key, vehicle)``."""
    z = counter_state(vehicle_state, tick)
    return box_muller(counter_uniform_from(z, 0), counter_uniform_from(z, 1))
