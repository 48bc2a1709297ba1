"""The run recorder of one vehicle: ``vehicle_N.csv`` (one row per control tick, the
simulator's columns, then the runner's extra columns) and ``vehicle_N.json`` (the run's
metadata) in a log directory; with ``bag`` (``deploy --bag``), the rows go to that ROS 2
bag too (``openconvoy.bag.BagWriter``), which is closed with the log."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from openconvoy.logs import LogWriter


class RunRecorder:
    """Records vehicle ``vehicle_id``'s run in ``log_dir`` (None: records nothing).
    ``extra_columns`` follow DESIGN.md's columns in the CSV."""

    def __init__(
        self, log_dir: str | Path | None, vehicle_id: int, extra_columns: Sequence[str] = ()
    ) -> None:
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.vehicle_id = vehicle_id
        self.extra_columns = tuple(extra_columns)
        self._writer: LogWriter | None = None
        self.bag: Any = None

    @property
    def recording(self) -> bool:
        """True between ``open`` and ``close`` with a log directory."""
        return self._writer is not None

    def open(self) -> None:
        """Create the CSV (its header written); nothing without a log directory."""
        if self.log_dir is not None and self._writer is None:
            self._writer = LogWriter(
                self.log_dir / f"vehicle_{self.vehicle_id}.csv", extra_columns=self.extra_columns
            )

    def row(self, row: Mapping[str, Any]) -> None:
        """One tick's row (flushed by ``LogWriter`` as it sees fit, closed by ``close``)."""
        if self._writer is not None:
            self._writer.write(dict(row))
            if self.bag is not None:
                self.bag.row(row)

    def close(self, metadata: Mapping[str, Any]) -> None:
        """Close the CSV and write ``metadata`` as ``vehicle_N.json`` (once)."""
        if self._writer is None or self.log_dir is None:
            return
        self._writer.close()
        if self.bag is not None:
            self.bag.close()
        self._writer = None
        path = self.log_dir / f"vehicle_{self.vehicle_id}.json"
        path.write_text(json.dumps(dict(metadata), indent=2, default=str) + "\n", encoding="utf-8")
