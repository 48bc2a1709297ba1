"""The run log: one CSV row per vehicle per control tick, the same in sim and on vehicles.

Columns are DESIGN.md's, in its order; extra columns may follow. A simulator run writes one
file; a vehicle run writes one file per vehicle, and ``read_log`` on a directory merges all
``*.csv`` logs in it, ordered by ``t_s`` then ``vehicle_id``. Rows are flushed as written, so
Ctrl-C or SIGTERM loses nothing already logged.
"""

from __future__ import annotations

import csv
import math
from array import array
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
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


@dataclass(frozen=True, slots=True)
class TickSnapshot:
    """One tick of a whole convoy, one entry per vehicle (leader first) in each field:
    what its log rows report. Units as the columns say (``COLUMNS``); ``extra`` holds
    further columns by name (a world with more in it, such as traffic)."""

    t_s: float
    x_m: Sequence[float]
    y_m: Sequence[float]
    lat_deg: Sequence[float]
    lon_deg: Sequence[float]
    speed_mps: Sequence[float]
    heading_rad: Sequence[float]
    accel_mps2: Sequence[float]
    cmd_speed_mps: Sequence[float]
    cmd_heading_change_rad: Sequence[float]
    mode: Sequence[str]
    gap_m: Sequence[float]
    desired_gap_m: Sequence[float]
    spacing_error_m: Sequence[float]
    msgs_sent: Sequence[int]
    msgs_received: Sequence[int]
    msgs_lost: Sequence[int]
    pred_msg_age_s: Sequence[float]
    extra: Mapping[str, Sequence[Any]] = field(default_factory=dict)


def snapshot_rows(snap: TickSnapshot) -> list[dict[str, Any]]:
    """The log rows (``COLUMNS`` order, then ``extra``'s) of every vehicle in ``snap``."""
    per_vehicle = [getattr(snap, c) for c in COLUMNS[2:]]
    rows = []
    for i in range(len(snap.x_m)):
        row: dict[str, Any] = {"t_s": snap.t_s, "vehicle_id": i}
        row.update(zip(COLUMNS[2:], (values[i] for values in per_vehicle)))
        for name, values in snap.extra.items():
            row[name] = values[i]
        rows.append(row)
    return rows


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
        self.columns: tuple[str, ...] = COLUMNS + tuple(
            c for c in extra_columns if c not in COLUMNS
        )
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
    if not path.is_file():  # a FIFO would block, a device never end
        return False
    try:
        with path.open(encoding="utf-8") as f:
            header = f.readline().strip().split(",")
    except UnicodeDecodeError:
        return False
    return header[:2] == ["t_s", "vehicle_id"]


def read_log(path: str | Path) -> Log:
    """Read a log file or merge a directory of per-vehicle logs, sorted by time then vehicle;
    a ROS 2 bag of a run (``sim``/``deploy --bag``), or a directory of them, reads the same.

    A log that is not one (binary, no data rows, a value that is not a number, a mode not
    in ``MODES``, a non-finite time or position, the same vehicle twice at one time) is an
    ``InputFileError`` naming the file, the line and the column.
    """
    return read_log_counted(path)[0]


INVALID_COLUMN = "telemetry_valid"
"""A deploy log's row flag: 0 = written while the autopilot's telemetry was lost (its
measured values are NaN, not repeated). ``read_log`` leaves such rows out."""


def read_log_counted(path: str | Path) -> tuple[Log, dict[int, int]]:
    """``read_log``, and how many rows each vehicle's log marked invalid (``INVALID_COLUMN``
    0: no telemetry) and were left out (vehicle id -> rows; empty when none)."""
    if _is_bag_run(Path(path)):
        from openconvoy.bag import read_bag  # a ROS 2 bag (sim/deploy --bag): see bag.py

        return read_bag(path), {}
    read = [_read_one(f) for f in log_files(path)]
    parts: list[Log] = [p for p, _ in read]
    left_out: dict[int, int] = {}
    for _, counts in read:
        for vid, n in counts.items():
            left_out[vid] = left_out.get(vid, 0) + n
    columns = [c for c in parts[0] if all(c in p for p in parts)]
    merged = {c: np.concatenate([p[c] for p in parts]) for c in columns}
    order = np.lexsort((merged["vehicle_id"], merged["t_s"]))
    return {c: v[order] for c, v in merged.items()}, left_out


def _is_bag_run(p: Path) -> bool:
    """A ROS 2 bag (a directory with ``metadata.yaml``, or a file in one), or a directory
    holding bags and no CSV log: what ``openconvoy.bag.read_bag`` reads."""
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return True
        if any(_is_log(f) for f in p.glob("*.csv")):
            return False
        return any((d / "metadata.yaml").is_file() for d in p.iterdir() if d.is_dir())
    return p.suffix == ".mcap" and (p.parent / "metadata.yaml").is_file()


MAX_VEHICLE_ID = 1000
"""The largest vehicle id a log may hold (a leader and at most 1,000 followers)."""

_FINITE_COLUMNS = ("t_s", "x_m", "y_m")
"""Columns every row must carry as finite numbers."""


def _read_one(path: Path) -> tuple[Log, dict[int, int]]:
    """One CSV log as columns, converted row by row into compact arrays (8 bytes a value;
    a 1 h, 3-vehicle run is 216,000 rows), never held as strings; without the rows marked
    invalid, counted per vehicle. Only a regular file: a FIFO or a device (``/dev/zero``)
    would block or never end (D57)."""
    try:
        if path.exists() and not path.is_file():
            raise InputFileError(f"{path}: not a regular file (a log is a CSV file)")
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise InputFileError(f"{path}: empty log file")
            missing = [c for c in COLUMNS if c not in header]
            if missing:
                raise InputFileError(
                    f"{path}: not an OpenConvoy log, missing column(s): {', '.join(missing)}"
                )
            columns, lines = _columns(path, header, reader)
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a text file (an OpenConvoy log is CSV text)") from None
    except csv.Error as exc:
        raise InputFileError(f"{path}: not a CSV file ({exc})") from None
    if not lines:
        raise InputFileError(f"{path}: the log has a header but no data rows")
    out: Log = {}
    for name, values in zip(header, columns):
        if name in _TEXT_COLUMNS:
            out[name] = np.array(values, dtype=object)
        elif name in _INT_COLUMNS:
            out[name] = (
                np.frombuffer(values, dtype=np.int64).copy()
                if len(values)
                else np.zeros(0, np.int64)
            )
        else:
            out[name] = (
                np.frombuffer(values, dtype=np.float64).copy() if len(values) else np.zeros(0)
            )
    left_out: dict[int, int] = {}
    if INVALID_COLUMN in out:
        keep = out[INVALID_COLUMN] != 0
        for vid in out["vehicle_id"][~keep]:
            left_out[int(vid)] = left_out.get(int(vid), 0) + 1
        out = {c: v[keep] for c, v in out.items()}
        lines = [n for n, k in zip(lines, keep) if k]
        if not lines:
            raise InputFileError(f"{path}: every row is marked invalid (no telemetry)")
    _check_rows(path, out, lines)
    return out, left_out


def _columns(path: Path, header: list[str], reader: Any) -> tuple[list[Any], list[int]]:
    """Per-column arrays and the file line of each row; a torn last line is skipped."""
    kinds = [2 if n in _TEXT_COLUMNS else 1 if n in _INT_COLUMNS else 0 for n in header]
    columns: list[Any] = [[] if k == 2 else array("q") if k == 1 else array("d") for k in kinds]
    texts: dict[str, str] = {}  # one object per distinct mode value
    lines: list[int] = []
    width = len(header)
    for n, row in enumerate(reader, start=2):
        if len(row) != width:
            continue
        for i, (kind, v) in enumerate(zip(kinds, row)):
            try:
                if kind == 0:
                    columns[i].append(float(v) if v else math.nan)
                elif kind == 1:
                    columns[i].append(int(float(v)) if v else -1)
                else:
                    columns[i].append(texts.setdefault(v, v))
            except (ValueError, OverflowError):
                raise InputFileError(
                    f"{path}:{n}: column {header[i]}: {v!r} is not a number"
                ) from None
        lines.append(n)
    return columns, lines


def _check_rows(path: Path, log: Log, lines: list[int]) -> None:
    """The checks on values ``read_log`` promises (see there)."""
    for name in _FINITE_COLUMNS:
        bad = np.flatnonzero(~np.isfinite(log[name]))
        if bad.size:
            k = int(bad[0])
            raise InputFileError(
                f"{path}:{lines[k]}: column {name}: {float(log[name][k])!r} (must be a finite number)"
            )
    bad_mode = [k for k, m in enumerate(log["mode"]) if m not in MODES]
    if bad_mode:
        k = bad_mode[0]
        raise InputFileError(
            f"{path}:{lines[k]}: column mode: {log['mode'][k]!r} is not one of {', '.join(MODES)}"
        )
    vid = log["vehicle_id"]
    bad = np.flatnonzero((vid < 0) | (vid > MAX_VEHICLE_ID))
    if bad.size:
        k = int(bad[0])
        raise InputFileError(
            f"{path}:{lines[k]}: column vehicle_id: {int(vid[k])} (a convoy's vehicles are "
            f"0..{MAX_VEHICLE_ID})"
        )
    for v in np.unique(vid):
        rows = np.flatnonzero(vid == v)
        back = np.flatnonzero(np.diff(log["t_s"][rows]) < 0.0)
        if back.size:
            k = int(rows[back[0] + 1])
            raise InputFileError(
                f"{path}:{lines[k]}: column t_s: vehicle {int(v)}'s time goes back to "
                f"{float(log['t_s'][k])!r} s (rows must be in time order)"
            )
    keys = np.stack([log["t_s"], log["vehicle_id"].astype(float)], axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        k = int(first[np.flatnonzero(counts > 1)[0]])
        raise InputFileError(
            f"{path}:{lines[k]}: vehicle {int(log['vehicle_id'][k])} appears more than once at t_s = {float(log['t_s'][k])!r}"
        )
