"""Simulated GPS noise: white Gaussian position noise, drawn counter-based.

Each vehicle's position fix at tick ``k`` is off by ``sigma * (z_x, z_y)``, two
independent standard normals from one Box-Muller pair of counter-based uniforms
(``comms.loss.counter_uniform(key, vehicle, k, j)``, ``j = 0, 1``). The draws depend only on
(key, vehicle, tick), not on the order vehicles or convoys are visited in, so the batched
simulator (``envs.vector.gps``) makes the same ones in a compiled kernel.
"""

from __future__ import annotations

import math

import numpy as np

from openconvoy.comms.loss import counter_state, counter_uniform_from


def gps_key(rng: np.random.Generator) -> int:
    """An episode's GPS key, drawn from its GPS generator."""
    return int(rng.integers(2**63))


def vehicle_states(key: int, n_vehicles: int) -> list[int]:
    """Each vehicle's counter state (the key and vehicle hashed once per episode)."""
    return [counter_state(key, i) for i in range(n_vehicles)]


def box_muller(u1: float, u2: float) -> tuple[float, float]:
    """Two independent standard normals from two uniforms in [0, 1)."""
    r = math.sqrt(-2.0 * math.log(1.0 - u1))
    angle = 2.0 * math.pi * u2
    return r * math.cos(angle), r * math.sin(angle)


def gps_noise(states: list[int], sigma_m: float, tick: int) -> tuple[list[float], list[float]]:
    """The east and north position errors (m) of every vehicle at ``tick``."""
    dx, dy = [], []
    for st in states:
        z = counter_state(st, tick)
        nx, ny = box_muller(counter_uniform_from(z, 0), counter_uniform_from(z, 1))
        dx.append(sigma_m * nx)
        dy.append(sigma_m * ny)
    return dx, dy
