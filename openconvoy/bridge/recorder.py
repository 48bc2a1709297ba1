"""The run recorder of one vehicle: ``vehicle_N.csv`` (one row per control tick, the
simulator's columns, then the runner's extra columns) and ``vehicle_N.json`` (the run's
metadata) in a log directory; with ``bag`` (``deploy --bag``), the rows go to that ROS 2
bag too (``openconvoy.bag.BagWriter``), which is closed with the log.

Both files are created exclusively when the run opens its log (before connecting): a
second deploy of the same vehicle into the same directory is refused instead of mixing
its rows into the first one's file (D65). The metadata file is written at once, padded
to ``METADATA_RESERVE_BYTES``, and overwritten in place at the end, so that a disk that
fills up during the run (D54) still gets its metadata. A row that cannot be written stops
the recording (``failed`` says why) instead of raising into the control loop.
"""

from __future__ import annotations

import errno
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from openconvoy.core.errors import OutputPathError
from openconvoy.logs import LogWriter

METADATA_RESERVE_BYTES = 32 * 1024
"""Room kept for ``vehicle_N.json`` from the start (a run's metadata is 2-5 KiB; a long
list of failsafe events is cut to fit when the disk is full)."""


class RunRecorder:
    """Records vehicle ``vehicle_id``'s run in ``log_dir`` (None: records nothing).
    ``extra_columns`` follow DESIGN.md's columns in the CSV.

    Attributes:
        failed: why writing stopped during the run ("" while it works).
        created: whether ``open`` created the files and ``close`` has not yet run.
        written: the CSV this recorder created (None before ``open``): what an exit line
            may claim.
    """

    def __init__(
        self, log_dir: str | Path | None, vehicle_id: int, extra_columns: Sequence[str] = ()
    ) -> None:
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.vehicle_id = vehicle_id
        self.extra_columns = tuple(extra_columns)
        self._writer: LogWriter | None = None
        self.bag: Any = None
        self.failed = ""
        self.created = False
        self.written: Path | None = None

    @property
    def csv_path(self) -> Path | None:
        return None if self.log_dir is None else self.log_dir / f"vehicle_{self.vehicle_id}.csv"

    @property
    def json_path(self) -> Path | None:
        return None if self.log_dir is None else self.log_dir / f"vehicle_{self.vehicle_id}.json"

    @property
    def recording(self) -> bool:
        """True between ``open`` and ``close`` with a log directory, while writing works."""
        return self._writer is not None

    def open(self) -> None:
        """Create the CSV (its header written) and the reserved metadata file, both
        exclusively; nothing without a log directory, nothing when already open.

        Raises ``OutputPathError`` (one line) when either file exists or cannot be
        created (a full disk, no permission)."""
        csv_path, json_path = self.csv_path, self.json_path
        if csv_path is None or json_path is None or self.created:
            return
        self.check_free()
        made: list[Path] = []
        try:
            csv_path.parent.mkdir(parents=True, exist_ok=True)
            for path in (csv_path, json_path):
                os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
                made.append(path)
            placeholder = {
                "kind": "deploy",
                "vehicle_id": self.vehicle_id,
                "exit_reason": "running, or ended without its final metadata (killed)",
            }
            _write_in_place(json_path, _padded(placeholder, METADATA_RESERVE_BYTES))
            self._writer = LogWriter(csv_path, extra_columns=self.extra_columns)
        except OSError as exc:
            for path in made:
                path.unlink(missing_ok=True)
            if exc.errno == errno.EEXIST:
                raise OutputPathError(
                    f"--log {self.log_dir}: {Path(exc.filename or csv_path).name} was just "
                    f"created by another deploy of vehicle {self.vehicle_id}: give another --log"
                ) from None
            raise OutputPathError(
                f"--log {self.log_dir}: cannot create the log ({exc.strerror or exc})"
            ) from None
        self.created, self.written = True, csv_path

    def check_free(self) -> None:
        """Refuse early (``OutputPathError``, one line) when this vehicle's log files
        already exist in the directory; ``open`` checks again, atomically."""
        for path in (self.csv_path, self.json_path):
            if path is not None and path.exists():
                raise OutputPathError(
                    f"--log {self.log_dir}: {path.name} exists (another deploy of vehicle "
                    f"{self.vehicle_id} writes there, or an earlier run): give another --log"
                )

    def row(self, row: Mapping[str, Any]) -> bool:
        """One tick's row (flushed by ``LogWriter``). False when it could not be written:
        the recording stops there (``failed`` says why; the metadata is still written)."""
        if self._writer is None:
            return False
        try:
            self._writer.write(dict(row))
            if self.bag is not None:
                self.bag.row(row)
            return True
        except OSError as exc:
            self.failed = f"{self.csv_path}: {exc.strerror or exc}"
            self._close_writer()
            return False

    def _close_writer(self) -> str:
        """Close the CSV (and the bag); why that failed ("" if it did not)."""
        writer, self._writer = self._writer, None
        bag, self.bag = self.bag, None
        if writer is None:
            return ""
        try:
            writer.close()
            if bag is not None:
                bag.close()
        except OSError as exc:
            return f"{self.csv_path}: {exc.strerror or exc}"
        return ""

    def close(self, metadata: Mapping[str, Any]) -> str:
        """Close the CSV and write ``metadata`` as ``vehicle_N.json`` (into its reserved
        room; the failsafe events cut to fit if the disk is full). Never raises: returns
        why something could not be written ("" when all was)."""
        json_path = self.json_path
        if not self.created or json_path is None:
            return ""
        self.created = False  # once
        why = self._close_writer() or ""
        meta = dict(metadata)
        if self.failed:
            meta["log_write_failed"] = self.failed
        text = json.dumps(meta, indent=2, default=str) + "\n"
        try:
            if len(text.encode()) <= METADATA_RESERVE_BYTES:
                _write_in_place(json_path, text.encode())
            else:
                try:
                    _write_in_place(json_path, text.encode())
                except OSError:
                    _write_in_place(json_path, _cut_to_fit(meta).encode())
        except OSError as exc:
            why = why or f"{json_path}: {exc.strerror or exc}"
        return why


def _padded(obj: Mapping[str, Any], size: int) -> bytes:
    """``obj`` as JSON followed by spaces up to ``size`` bytes (still valid JSON)."""
    data = (json.dumps(dict(obj)) + "\n").encode()
    return data + b" " * max(0, size - len(data) - 1) + b"\n"


def _write_in_place(path: Path, data: bytes) -> None:
    """Overwrite ``path`` from its start with ``data`` and cut it there: no new blocks
    when ``data`` fits the file's reserved size."""
    fd = os.open(path, os.O_WRONLY)
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.ftruncate(fd, len(data))
        os.fsync(fd)
    finally:
        os.close(fd)


def _cut_to_fit(meta: dict[str, Any]) -> str:
    """``meta`` with its failsafe events cut so that it fits ``METADATA_RESERVE_BYTES``."""
    events = list(meta.get("failsafe_events") or [])
    keep = len(events)
    while True:
        cut = dict(meta, failsafe_events=events[:keep])
        if keep < len(events):
            cut["failsafe_events_cut"] = len(events) - keep
        text = json.dumps(cut, indent=2, default=str) + "\n"
        if len(text.encode()) <= METADATA_RESERVE_BYTES or keep == 0:
            return text
        keep //= 2
