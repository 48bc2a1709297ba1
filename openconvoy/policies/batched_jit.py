"""``BatchedClassical.act_batch`` compiled: ``policies.classical_rows`` through numba.

``policies.batched``'s rows would run as Python; this module compiles the same functions
(``classical_rows.act_rows`` and its helpers, and the controllers' laws of
``core.controllers`` they call) with numba's ``njit``: one loop over rows, ~40 µs for
1,024 x 2 rows, the same IEEE doubles in the same order as ``ClassicalPolicy.act``
(no fastmath), so actions agree with ``act`` bit for bit (``tests/policies/test_batched_jit.py``).

Compiled with ``envs.vector.jit``'s options (no reference counting, numpy's error model)
but not through it: policies import ``core`` only (DESIGN.md's import rule). numba checks
a cached kernel against its own source file only, so the cache lives in a directory named
for a digest of every file compiled into it (``SOURCES``) and numba's version: a change to
a controller's law recompiles the kernel. Importing this module without numba raises
``DependencyMissing`` and ``BatchedClassical`` runs the rows as Python.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import Any

from openconvoy.core import controllers
from openconvoy.core.errors import DependencyMissing
from openconvoy.policies import classical_rows

try:
    import numba as _numba
    from numba.extending import register_jitable as _register_jitable
except ImportError as exc:  # pragma: no cover - the extra is installed by `make test`
    raise DependencyMissing(
        "a compiled act_batch needs numba: pip install 'openconvoy[batched]'"
    ) from exc

LAWS = ("speed_law", "pd_speed", "integrated", "clamp", "stanley", "pure_pursuit")
"""``core.controllers``'s functions the rows call, compiled where they are called."""
SOURCES = (controllers, classical_rows)
_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy", "_nrt": False}


def _cache_dir() -> str:
    """``~/.cache/openconvoy/classical-<digest>`` (``NUMBA_CACHE_DIR``, ``XDG_CACHE_HOME``
    move it; the temporary directory when not writable)."""
    digest = hashlib.sha256(_numba.__version__.encode())
    for module in SOURCES:
        assert module.__file__ is not None
        digest.update(Path(module.__file__).read_bytes())
    digest.update(Path(__file__).read_bytes())
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(home, "openconvoy")
    path = Path(base) / f"classical-{digest.hexdigest()[:16]}"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home
        path = Path(tempfile.gettempdir()) / "openconvoy" / path.name
        path.mkdir(parents=True, exist_ok=True)
    return str(path)


def _compile() -> Any:
    """``classical_rows.act_rows`` compiled, its helpers and laws inlined."""
    inline = {k: v for k, v in _OPTIONS.items() if k != "cache"}
    for module, names in ((controllers, LAWS), (classical_rows, classical_rows.ROW_FUNCTIONS)):
        for name in names:
            _register_jitable(forceinline=True, **inline)(getattr(module, name))
    config: Any = _numba.config
    saved = config.CACHE_DIR
    config.CACHE_DIR = _cache_dir()
    try:
        return _numba.njit(**_OPTIONS)(classical_rows.act_rows)
    finally:
        config.CACHE_DIR = saved


act_rows = _compile()
"""``classical_rows.act_rows`` compiled (same arguments)."""
pack = classical_rows.pack
