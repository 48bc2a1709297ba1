"""The batched simulator's compiler: numba's ``njit``, cached on disk.

The ``VectorConvoyEnv`` kernels are loops over convoys and vehicles compiled to machine
code (numba, the ``batched`` extra), not Python loops: one call per stage of the tick
instead of ~1,000 numpy calls. ``cache=True`` keeps the compiled code next to the
sources, so only the first process after an install pays the compile (a few seconds).
No ``fastmath``: the kernels keep IEEE arithmetic, so they agree with ``ConvoyEnv``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from openconvoy.core.errors import ConfigError

try:
    import numba as _numba
except ImportError as exc:  # pragma: no cover - the extra is installed by `make test`
    raise ConfigError("VectorConvoyEnv needs numba: pip install 'openconvoy[batched]'") from exc


def kernel(fn: Callable[..., Any]) -> Any:
    """Compile ``fn`` in nopython mode, cached (no GIL release, no fastmath)."""
    return _numba.njit(cache=True, nogil=True)(fn)
