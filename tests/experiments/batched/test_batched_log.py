"""Logs from arrays: ``round6`` is Python's ``round(v, 6)`` bit for bit, and ``csv_bytes``
is the file ``LogWriter`` writes, byte for byte (``logs.read_log`` reads it back)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.experiments.batched.log import csv_bytes, round6, rounded
from openconvoy.logs import COLUMNS, LogWriter, read_log


def _bits(values: list[float]) -> list[bytes]:
    return [struct.pack("<d", v) for v in values]


def _python_round(values: list[float]) -> list[float]:
    return [v if not math.isfinite(v) else round(v, 6) for v in values]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=50))
def test_round6_is_pythons_round_on_any_float(values: list[float]) -> None:
    got = round6(np.array(values, dtype=float)).tolist()
    assert _bits(got) == _bits(_python_round(values))


@settings(max_examples=200, deadline=None)
@given(
    st.integers(-(10**12), 10**12),
    st.integers(-4, 4),
    st.sampled_from([1, -1]),
)
def test_round6_on_values_next_to_a_half_of_the_last_digit(n: int, ulps: int, sign: int) -> None:
    # (n + 0.5) * 1e-6, nudged by a few ulps either way: the cases where scaling by 1e6
    # and rounding to an integer may land on the other side of the half.
    x = sign * (n + 0.5) / 1e6
    for _ in range(abs(ulps)):
        x = math.nextafter(x, math.inf if ulps > 0 else -math.inf)
    assert _bits(round6(np.array([x])).tolist()) == _bits([round(x, 6)])


def test_round6_keeps_signs_of_zero_and_non_finite_values() -> None:
    got = round6(np.array([-1e-9, 0.0, -0.0, math.nan, math.inf, -math.inf, 1e300]))
    assert _bits(got[:3].tolist()) == _bits([-0.0, 0.0, -0.0])
    assert math.isnan(got[3]) and got[4] == math.inf and got[5] == -math.inf
    assert got[6] == round(1e300, 6)


def _rows() -> list[dict]:
    values = [0.0, -0.0, 1.5e-5, -2.25e-7, 28.6024, -81.2001234567, 1e7 + 0.1234565, math.nan]
    out = []
    for k, v in enumerate(values):
        row = {c: v * (i + 1) for i, c in enumerate(COLUMNS)}
        row.update(
            vehicle_id=k % 3,
            t_s=round(0.05 * k, 9),
            x_m=float(k),
            y_m=0.0,
            mode=("coop", "degraded", "stop", "failsafe")[k % 4],
            msgs_sent=k,
            msgs_received=2 * k,
            msgs_lost=-1 if k == 3 else k,
            length_m=0.779,
        )
        out.append(row)
    return out


def _as_columns(rows: list[dict], columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    ints = {"vehicle_id", "msgs_sent", "msgs_received", "msgs_lost"}
    out = {}
    for c in columns:
        values = [r[c] for r in rows]
        dtype = object if c == "mode" else np.int64 if c in ints else float
        out[c] = np.array(values, dtype=dtype)
    return out


def test_csv_bytes_are_what_logwriter_writes(tmp_path: Path) -> None:
    columns = COLUMNS + ("length_m",)
    rows = _rows()
    path = tmp_path / "log.csv"
    with LogWriter(path, extra_columns=("length_m",)) as w:
        w.write_many(rows)
    log = rounded(_as_columns(rows, columns))
    assert csv_bytes(log, columns) == path.read_bytes()
    # ``rounded`` is what read_log gives back for the written file.
    back = read_log(path)
    for c in columns:
        if back[c].dtype.kind == "f":
            same_nan = [0.0 if math.isnan(v) else v for v in log[c].tolist()]
            assert _bits([0.0 if math.isnan(v) else v for v in back[c].tolist()]) == _bits(
                same_nan
            ), c
        else:
            assert back[c].tolist() == log[c].tolist(), c


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(allow_nan=True, allow_infinity=True, width=64),
            st.floats(-1e-3, 1e-3),
            st.integers(0, 10**12),
        ),
        min_size=1,
        max_size=20,
    )
)
def test_csv_bytes_match_logwriter_on_any_values(tmp_path_factory, cells) -> None:
    path = tmp_path_factory.mktemp("log") / "log.csv"
    columns = ("t_s", "x_m", "msgs_sent")
    rows = [{"t_s": a, "x_m": b, "msgs_sent": c} for a, b, c in cells]
    with LogWriter(path) as w:
        w.write_many(rows)
    log = {
        "t_s": round6(np.array([r["t_s"] for r in rows])),
        "x_m": round6(np.array([r["x_m"] for r in rows])),
        "msgs_sent": np.array([r["msgs_sent"] for r in rows], dtype=np.int64),
    }
    written = path.read_bytes().split(b"\r\n", 1)[1]  # LogWriter writes every column
    want = [
        ",".join(line.split(",")[i] for i in (0, 2, 15))
        for line in written.decode().split("\r\n")[:-1]
    ]
    got = csv_bytes(log, columns).decode().split("\r\n")[1:-1]
    assert got == want
