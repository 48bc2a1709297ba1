"""GPS noise of the batched simulator: ``envs.gps``'s draws in a compiled kernel.

``sense`` writes what the members measure of themselves: the plant state with each
position off by ``envs.gps.gps_noise`` of its convoy's key, vehicle and tick (the same
numbers, libm's log, cos and sin on both sides).
"""

from __future__ import annotations

import numpy as np

from openconvoy.comms.loss import SPLITMIX_GOLDEN, UNIT_53
from openconvoy.envs import gps
from openconvoy.envs.vector.channel import _mix
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules

rules(gps, "box_muller")

_G, _S11 = np.uint64(SPLITMIX_GOLDEN), np.uint64(11)


@bare_inline
def counter_normals(key, vehicle, tick):  # pragma: no cover - compiled
    """``envs.gps.box_muller`` of the counter uniforms ``(key, vehicle, tick, 0)`` and
    ``(..., 1)`` (``comms.loss.counter_uniform``): two independent standard normals."""
    z = _mix(key + _G + np.uint64(vehicle))
    z = _mix(z + _G + np.uint64(tick))
    u1 = np.float64(_mix(z + _G + np.uint64(0)) >> _S11) * UNIT_53
    u2 = np.float64(_mix(z + _G + np.uint64(1)) >> _S11) * UNIT_53
    return gps.box_muller(u1, u2)


@bare_kernel
def sense(own, step, keys, sigma, rows, sensed):  # pragma: no cover - compiled
    """``sensed`` (6, B, N): ``own`` with GPS noise of std ``sigma`` (m) on x and y, at
    tick ``step[b]`` of convoy ``b`` keyed ``keys[b]``, for the convoys ``rows``: the
    errors of ``envs.gps.gps_noise``."""
    _, B, N = own.shape
    for b in range(B):
        if not rows[b]:
            continue
        for i in range(N):
            for f in range(6):
                sensed[f, b, i] = own[f, b, i]
            nx, ny = counter_normals(keys[b], i, step[b])
            sensed[0, b, i] += sigma * nx
            sensed[1, b, i] += sigma * ny
