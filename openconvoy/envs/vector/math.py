"""Plane geometry for the batched kernels: lengths and angles, compiled."""

from __future__ import annotations

import math

from openconvoy.core import state
from openconvoy.envs.vector.jit import bare_inline, rules


@bare_inline
def norm(dx, dy):  # pragma: no cover - compiled
    """Euclidean length of (dx, dy): sqrt(dx² + dy²) (within an ulp of ``math.hypot``,
    a tenth of its cost; no overflow at vehicle distances)."""
    return math.sqrt(dx * dx + dy * dy)


rules(state, "wrap_angle")
wrap = state.wrap_angle
"""An angle (rad) into [-π, π): ``core.state.wrap_angle``, compiled where a kernel calls it."""
