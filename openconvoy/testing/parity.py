"""Two paths to the same numbers: deep equality and directory trees compared file by file.

What the parity tests use to hold, for example, a batched sweep's files byte-identical to
the per-run sweep's, or two rollouts of one seed equal to the bit.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np


def same(a: Any, b: Any) -> bool:
    """``a`` and ``b`` equal to the bit, through dicts (same keys), tuples and lists (same
    length), numpy arrays (same dtype, NaN equal to NaN; object arrays element by element)
    and floats (NaN equal to NaN)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        if a.dtype == object:  # strings and mixed values: NaN is not theirs to hold
            return isinstance(b, np.ndarray) and b.dtype == object and a.tolist() == b.tolist()
        return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return bool(a == b)


def tree_files(root: str | Path, skip: tuple[str, ...] = ()) -> dict[str, bytes]:
    """Every file under ``root`` (recursively) as ``{path relative to root: bytes}``, in
    sorted order, leaving out files named in ``skip`` (say a manifest naming its own
    directory)."""
    root = Path(root)
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name not in skip
    }


__all__ = ["same", "tree_files"]
