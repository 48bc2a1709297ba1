"""The firmware convoy runs of ``tests/data`` (gzipped deploy logs), unpacked for a test."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

DATA = Path(__file__).resolve().parent / "data"
SITL_CONVOY = DATA / "sitl-convoy"
"""ArduPilot Rover 4.7 SITL convoy runs (``tests/data/sitl-convoy/README.md``)."""
PX4_CONVOY = DATA / "sitl-px4-convoy"
"""PX4 SIH rover convoy runs (``tests/data/sitl-px4-convoy/README.md``)."""


def unpack(run: str, into: Path, data: Path = SITL_CONVOY) -> Path:
    """A recorded run as deploy wrote it (CSV logs + metadata) under ``into``."""
    out = into / run
    out.mkdir(parents=True)
    for f in (data / run).iterdir():
        if f.name.endswith(".csv.gz"):
            with gzip.open(f, "rb") as src, (out / f.name[:-3]).open("wb") as dst:
                shutil.copyfileobj(src, dst)
        else:
            shutil.copy(f, out / f.name)
    return out
