"""Run logs from arrays: the columns, the CSV bytes and the read-back values of a log that
``LogWriter`` would write, without a Python call per row.

A batched run (``experiments.batched.run``) holds every tick of every run in arrays; a sweep
writes each run's ``log.csv`` and computes its metrics from the log as read back (what
``openconvoy report`` recomputes). ``round6`` gives, for a whole array, the floats
``LogWriter`` writes and ``read_log`` reads back (``float(repr(round(v, 6)))`` equals
``round(v, 6)``), bit for bit; ``csv_bytes`` the file ``LogWriter`` writes, byte for byte.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

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


_FIXED_BELOW = 8e9
"""Below this, the ``repr`` of a ``round6``-ed float is its six-decimal value with the
trailing zeros cut (one kept): no shorter decimal lies within its half ulp."""
_TEXT = 24
"""Bytes a value's text may take: the longest ``repr`` of a float (``-1.2e-308`` with 17
digits)."""
_CELL = 28
"""Bytes of a cell: seven 4-byte words, so that each group of digits is one word written.
A number ``[-]WHOLE[.FRAC]`` is laid out as: sign at byte 3; twelve digit places at 4-15
(the whole part right-aligned, < 1e10); ``.`` and three fraction digits at 16-19, three
more at 20-22; the separator (``,`` or ``\\r\\n``) at 24-25. ``keep`` masks the bytes of
the text; text that is not such a number is written left-aligned from byte 0."""


def _words(texts: list[str]) -> np.ndarray:
    """Texts of at most 4 bytes as one native uint32 word each (their bytes in order)."""
    raw = np.zeros((len(texts), 4), dtype=np.uint8)
    for i, t in enumerate(texts):
        raw[i, : len(t)] = np.frombuffer(t.encode(), dtype=np.uint8)
    return raw.view(np.uint32)[:, 0]


_DIGITS4 = _words([f"{i:04d}" for i in range(10_000)])
_FRAC_HIGH = _words([f".{i:03d}" for i in range(1000)])
_FRAC_LOW = _words([f"{i:03d}" for i in range(1000)])
_SIGN = _words(["\0\0\0-"])[0]
_SEPARATOR = _words([",", "\r\n"])
_TEN_POWERS = 10 ** np.arange(1, 11, dtype=np.int64)
_TRAILING = np.array([len(f"{i:03d}") - len(f"{i:03d}".rstrip("0")) for i in range(1000)])
"""Trailing zeros of each three-digit group 000..999."""


def _keep_table() -> np.ndarray:
    """Which bytes of a number's cell are text, by (negative, digits 1..10 of the whole
    part, fraction digits 0..6 with 0 = no fraction, last column)."""
    table = np.zeros((2, 11, 7, 2, _CELL), dtype=bool)
    for neg in (0, 1):
        for count in range(1, 11):
            for nf in range(7):
                for last in (0, 1):
                    k = table[neg, count, nf, last]
                    k[3] = bool(neg)
                    k[16 - count : 16] = True
                    if nf:
                        k[16] = True
                        k[17 : 17 + min(nf, 3)] = True
                        k[20 : 20 + max(nf - 3, 0)] = True
                    k[24 : 25 + last] = True
    return table


_KEEP = _keep_table()


def _numbers(
    words: np.ndarray, neg: np.ndarray, whole: np.ndarray, frac: Any, last: int
) -> np.ndarray:
    """Write the numbers ``[-]WHOLE[.FRAC]`` (``whole`` < 1e10; ``frac`` in millionths,
    trailing zeros cut, one kept; or None) into ``words`` (rows, 7); their keep masks."""
    words[:, 0] = np.where(neg, _SIGN, 0)
    words[:, 1] = _DIGITS4[whole // 10**8]
    words[:, 2] = _DIGITS4[(whole // 10**4) % 10**4]
    words[:, 3] = _DIGITS4[whole % 10**4]
    count = np.searchsorted(_TEN_POWERS, whole, side="right") + 1
    if frac is None:
        nf = np.zeros(len(whole), dtype=np.int64)
    else:
        high, low = frac // 1000, frac % 1000
        words[:, 4] = _FRAC_HIGH[high]
        words[:, 5] = _FRAC_LOW[low]
        zeros = np.where(low != 0, _TRAILING[low], 3 + _TRAILING[high])
        nf = np.maximum(6 - zeros, 1)
    return _KEEP[neg.astype(np.int64), count, nf, last]


def _texts(words: np.ndarray, values: list[str], last: int) -> np.ndarray:
    """Write texts left-aligned into ``words`` (rows, 7); their keep masks."""
    cells = words.view(np.uint8)
    keep = np.zeros((len(values), _CELL), dtype=bool)
    for i, v in enumerate(values):
        b = v.encode("utf-8")
        if len(b) > _TEXT:
            raise ValueError(f"log value {v!r} is longer than {_TEXT} bytes")
        cells[i, : len(b)] = np.frombuffer(b, dtype=np.uint8)
        keep[i, : len(b)] = True
    keep[:, 24 : 25 + last] = True
    return keep


def _column(column: np.ndarray, last: int) -> tuple[np.ndarray, np.ndarray]:
    """``LogWriter``'s text of each value of a column (floats already ``round6``-ed) as
    cells: ``(rows, _CELL)`` bytes and the mask of those that are text."""
    n = len(column)
    words = np.zeros((n, _CELL // 4), dtype=np.uint32)
    words[:, 6] = _SEPARATOR[last]
    if column.dtype.kind not in "fiu":
        kinds, index = np.unique(column.astype(str), return_inverse=True)
        w = np.zeros((len(kinds), _CELL // 4), dtype=np.uint32)
        w[:, 6] = _SEPARATOR[last]
        keep = _texts(w, kinds.tolist(), last)
        return w.view(np.uint8)[index], keep[index]
    is_float = column.dtype.kind == "f"
    v = column.astype(np.float64 if is_float else np.int64)
    a = np.abs(v)
    fast = (a < _FIXED_BELOW) & ((a >= 1e-4) | (a == 0)) if is_float else a < 10**10
    keep = np.zeros((n, _CELL), dtype=bool)
    rows = slice(None) if fast.all() else np.flatnonzero(fast)
    w = words[rows]
    if is_float:
        scaled = np.rint(a[rows] * 1e6).astype(np.int64)
        keep[rows] = _numbers(w, np.signbit(v[rows]), scaled // 10**6, scaled % 10**6, last)
    else:
        keep[rows] = _numbers(w, v[rows] < 0, a[rows], None, last)
    words[rows] = w
    slow = np.flatnonzero(~fast & ~np.isnan(v) if is_float else ~fast)
    if len(slow):
        w = words[slow]
        w[:, :6] = 0
        keep[slow] = _texts(w, [repr(x) if is_float else str(x) for x in v[slow].tolist()], last)
        words[slow] = w
    keep[np.flatnonzero(np.isnan(v)) if is_float else [], 24 : 25 + last] = True
    return words.view(np.uint8), keep


def csv_bytes(log: Log, columns: Sequence[str]) -> bytes:
    """The bytes ``LogWriter(path, extra_columns=...)`` writes for ``log``'s rows, its
    ``columns`` in order (float columns given ``round6``-ed: see ``rounded``)."""
    head = (",".join(columns) + "\r\n").encode("utf-8")
    if len(log[columns[0]]) == 0:
        return head
    cells = [_column(np.asarray(log[c]), int(j == len(columns) - 1)) for j, c in enumerate(columns)]
    text = np.stack([t for t, _ in cells], axis=1)
    keep = np.stack([k for _, k in cells], axis=1)
    return head + text[keep].tobytes()
