"""How tests/data/sitl*/ were cut from the full firmware recordings (kept for provenance).

    python tests/data/trim_recordings.py FULL_DIR tests/data

FULL_DIR holds the recordings as recorded (``sitl/*.jsonl.gz``, ``sitl-px4/*.jsonl.gz``,
about 23 MB). Each output keeps the ``meta`` line, every message the recorder sent (``tx``:
what a replay sends to the simulated vehicle), every phase ``mark``, and of the received
messages (``rx``) only the types the tests read; records are unchanged and in order.
"""

from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path

BASE = {"HEARTBEAT", "STATUSTEXT", "COMMAND_ACK", "GLOBAL_POSITION_INT", "ATTITUDE"}
EXTRA = {
    # ArduPilot: servo outputs (conformance rows on telemetry timing, stops and timeouts).
    ("sitl", "telemetry_timing"): {"SERVO_OUTPUT_RAW"},
    ("sitl", "timeouts_and_stops"): {"SERVO_OUTPUT_RAW"},
    # PX4: the SIH simulator's true state (the conformance rows that measure true speed,
    # ``fit-plant --source truth``).
    ("sitl-px4", "setpoint_semantics"): {"HIL_STATE_QUATERNION"},
    ("sitl-px4", "speed_steps"): {"HIL_STATE_QUATERNION"},
    ("sitl-px4", "setpoint_loss"): {"HIL_STATE_QUATERNION"},
    ("sitl-px4", "stops"): {"HIL_STATE_QUATERNION"},
}
FIRST_ONLY = {("sitl-px4", "stops"): "DISTANCE_SENSOR"}  # the SIH's downward rangefinder


def trim(src: Path, dst: Path, keep: set[str], first_only: str | None) -> None:
    seen_first = False
    with gzip.open(src, "rt", encoding="utf-8") as f, open(dst, "wb") as raw:
        with gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=9, mtime=0) as out:
            out.write(f.readline().encode())
            for line in f:
                r = json.loads(line)
                kind = r.get("type")
                if r["dir"] == "rx" and kind not in keep:
                    if kind != first_only or seen_first:
                        continue
                    seen_first = True
                out.write(line.encode())


def main(full: Path, data: Path) -> None:
    for folder in ("sitl", "sitl-px4"):
        (data / folder).mkdir(parents=True, exist_ok=True)
        for src in sorted((full / folder).glob("*.jsonl.gz")):
            name = src.name.removesuffix(".jsonl.gz")
            keep = BASE | EXTRA.get((folder, name), set())
            trim(src, data / folder / src.name, keep, FIRST_ONLY.get((folder, name)))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
