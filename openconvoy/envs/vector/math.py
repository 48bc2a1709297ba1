"""Plane geometry for the batched kernels: lengths and angles, compiled."""

from __future__ import annotations

import math

from openconvoy.envs.vector.jit import bare_inline

TWO_PI = 2.0 * math.pi


@bare_inline
def norm(dx, dy):  # pragma: no cover - compiled
    """Euclidean length of (dx, dy): sqrt(dx² + dy²) (within an ulp of ``math.hypot``,
    a tenth of its cost; no overflow at vehicle distances)."""
    return math.sqrt(dx * dx + dy * dy)


@bare_inline
def wrap(a):  # pragma: no cover - compiled
    """An angle (rad) into [-π, π): ``np.remainder(a + π, 2π) - π``, the same rounding
    (fmod is exact; without a wrap, or one turn below, there is nothing to divide)."""
    x = a + math.pi
    if 0.0 <= x < TWO_PI:
        return x - math.pi
    if -TWO_PI <= x < 0.0:
        return (x + TWO_PI) - math.pi
    return x % TWO_PI - math.pi
