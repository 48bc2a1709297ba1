"""Run logs from arrays: the columns, the CSV bytes and the read-back values of a log that
``LogWriter`` would write, without a Python call per row.

A batched run (``experiments.batched``) holds every tick of every run in arrays; a sweep
writes each run's ``log.csv`` and computes its metrics from the log as read back (what
``openconvoy report`` recomputes). ``round6`` gives, for a whole array, the floats
``LogWriter`` writes and ``read_log`` reads back (``float(repr(round(v, 6)))`` equals
``round(v, 6)``), bit for bit; ``csv_bytes`` the file ``LogWriter`` writes, byte for byte.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openconvoy.logs import Log

_NEAR_HALF = 1e-3
"""How close to a half (in units of 1e-6) a scaled value must be for ``round6`` to ask
Python's ``round``: far more than the scaling's error for the magnitudes it handles."""
_EXACT_BELOW = 1e6
"""Magnitudes below which ``v * 1e6`` is within 1.2e-4 of the exact product."""


def round6(values: np.ndarray) -> np.ndarray:
    """``round(v, 6)`` of every element (Python's correctly rounded decimal rounding),
    bit for bit, NaN and infinities kept.

    ``rint(v * 1e6) / 1e6`` is the nearest double to the rounded decimal whenever the
    scaled value is not within ``_NEAR_HALF`` of a half; those few, and magnitudes
    beyond ``_EXACT_BELOW``, go through Python's ``round``."""
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # the huge ones go through round()
        scaled = v * 1e6
        out = np.rint(scaled) / 1e6
        near_half = np.abs(scaled - np.floor(scaled) - 0.5) < _NEAR_HALF
        odd = near_half | ~(np.abs(v) < _EXACT_BELOW)
    odd &= np.isfinite(v)
    if odd.any():
        out[odd] = [round(x, 6) for x in v[odd].tolist()]
    nonfinite = ~np.isfinite(v)
    out[nonfinite] = v[nonfinite]
    return out


def rounded(log: Log) -> Log:
    """``log`` as ``read_log`` returns the file ``LogWriter`` wrote from it: float
    columns rounded to 6 decimals (``round6``), the others as they are."""
    return {k: round6(v) if v.dtype.kind == "f" else v for k, v in log.items()}


def _texts(column: np.ndarray) -> list[str]:
    """``LogWriter``'s text of each value of a column (floats: already ``round6``-ed)."""
    if column.dtype.kind == "f":
        return ["" if x != x else repr(x) for x in column.tolist()]
    return [str(x) for x in column.tolist()]


def csv_bytes(log: Log, columns: Sequence[str]) -> bytes:
    """The bytes ``LogWriter(path, extra_columns=...)`` writes for ``log``'s rows, its
    ``columns`` in order (float columns given ``round6``-ed: see ``rounded``)."""
    texts = [_texts(log[c]) for c in columns]
    body = "\r\n".join(map(",".join, zip(*texts)))
    return (",".join(columns) + "\r\n" + body + ("\r\n" if body else "")).encode("utf-8")
