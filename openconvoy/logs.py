"""The run log: one CSV row per vehicle per control tick, the same in sim and on vehicles.

Columns are DESIGN.md's, in its order; extra columns may follow. A simulator run writes one
file; a vehicle run writes one file per vehicle, and ``read_log`` on a directory merges all
``*.csv`` logs in it, ordered by ``t_s`` then ``vehicle_id``. Rows are flushed as written, so
Ctrl-C or SIGTERM loses nothing already logged.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from openconvoy.core.errors import InputFileError, MissingFileError

COLUMNS: tuple[str, ...] = (
    "t_s",
    "vehicle_id",
    "x_m",
    "y_m",
    "lat_deg",
    "lon_deg",
    "speed_mps",
    "heading_rad",
    "accel_mps2",
    "cmd_speed_mps",
    "cmd_heading_change_rad",
    "mode",
    "gap_m",
    "desired_gap_m",
    "spacing_error_m",
    "msgs_sent",
    "msgs_received",
    "msgs_lost",
    "pred_msg_age_s",
)

MODES: tuple[str, ...] = ("coop", "degraded", "stop", "failsafe")
"""Values of the ``mode`` column."""

_TEXT_COLUMNS = {"mode"}
_INT_COLUMNS = {"vehicle_id", "msgs_sent", "msgs_received", "msgs_lost"}


def _format(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        return repr(round(value, 6))
    if isinstance(value, np.floating):
        return _format(float(value))
    return str(value)


class LogWriter:
    """Writes log rows to a CSV file, flushing every ``flush_every`` rows (1 = every row).

    Use as a context manager, or call ``close``. Missing values are written empty and read
    back as NaN.
    """

    def __init__(
        self,
        path: str | Path,
        extra_columns: Sequence[str] = (),
        flush_every: int = 1,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns: tuple[str, ...] = COLUMNS + tuple(c for c in extra_columns if c not in COLUMNS)
        self._file: IO[str] = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(self.columns)
        self._flush_every = max(1, flush_every)
        self._pending = 0
        self.rows = 0

    def write(self, row: Mapping[str, Any]) -> None:
        """Append one row; keys not in the columns are an error, missing keys are empty."""
        unknown = set(row) - set(self.columns)
        if unknown:
            raise KeyError(f"unknown log column(s): {', '.join(sorted(unknown))}")
        self._writer.writerow([_format(row.get(c)) for c in self.columns])
        self.rows += 1
        self._pending += 1
        if self._pending >= self._flush_every:
            self.flush()

    def write_many(self, rows: Iterable[Mapping[str, Any]]) -> None:
        for row in rows:
            self.write(row)

    def flush(self) -> None:
        if not self._file.closed:
            self._file.flush()
        self._pending = 0

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._file.close()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


Log = dict[str, np.ndarray]
"""A log in memory: column name -> array (floats, ints for id/counter columns, str for mode)."""


def log_files(path: str | Path) -> list[Path]:
    """The CSV log files a path designates: the file itself, or every log in a directory."""
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.glob("*.csv") if _is_log(f))
        if not files:
            raise MissingFileError(f"no OpenConvoy log (*.csv with a t_s column) in {p}")
        return files
    if not p.exists():
        raise MissingFileError(f"no such log file or directory: {p}")
    return [p]


def _is_log(path: Path) -> bool:
    with path.open(encoding="utf-8") as f:
        header = f.readline().strip().split(",")
    return header[:2] == ["t_s", "vehicle_id"]


def read_log(path: str | Path) -> Log:
    """Read a log file or merge a directory of per-vehicle logs, sorted by time then vehicle."""
    parts: list[Log] = [_read_one(f) for f in log_files(path)]
    columns = [c for c in parts[0] if all(c in p for p in parts)]
    merged = {c: np.concatenate([p[c] for p in parts]) for c in columns}
    order = np.lexsort((merged["vehicle_id"], merged["t_s"]))
    return {c: v[order] for c, v in merged.items()}


def _read_one(path: Path) -> Log:
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise InputFileError(f"{path}: empty log file")
        missing = [c for c in COLUMNS if c not in header]
        if missing:
            raise InputFileError(f"{path}: not an OpenConvoy log, missing column(s): {', '.join(missing)}")
        rows = [r for r in reader if len(r) == len(header)]  # a torn last line is skipped
    cols = list(zip(*rows)) if rows else [() for _ in header]
    out: Log = {}
    for name, values in zip(header, cols):
        if name in _TEXT_COLUMNS:
            out[name] = np.array(values, dtype=object)
        elif name in _INT_COLUMNS:
            out[name] = np.array([int(float(v)) if v else -1 for v in values], dtype=np.int64)
        else:
            out[name] = np.array([float(v) if v else math.nan for v in values], dtype=float)
    return out
