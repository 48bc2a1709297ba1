"""Inside a private mount namespace (``unshare -rm``): a small tmpfs is mounted as the log
directory, two deploy runners drive two simulated vehicles (real MAVLink over localhost
UDP) until the log disk is full (D54). Prints one JSON line with how each run ended.

Usage: unshare -rm python diskfull_driver.py OUT_DIR SIZE_KIB
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.bridge.*

from deploy_harness import make_convoy  # noqa: E402

from openconvoy.logs import read_log  # noqa: E402
from openconvoy.testing import wait_until  # noqa: E402


def main(out: Path, size_kib: int) -> dict:
    run = out / "run"
    run.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(run)], check=True
    )
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    logging.getLogger().addHandler(Keep(level=logging.WARNING))
    c = make_convoy(out, n=2, start=False)
    lines: list[list[str]] = [[], []]
    closed: list[list[str]] = [[], []]
    for i, car in enumerate(c.cars):
        car.runner.on_status = lines[i].append
        for name, obj in (("v2v", car.runner.v2v), ("link", car.link._link)):
            orig = obj.close

            def close(orig=orig, name=name, i=i) -> None:
                closed[i].append(name)
                orig()

            obj.close = close
    t0 = time.monotonic()
    for car in c.cars:
        car.start()
    moved = [0.0, 0.0]
    try:
        while any(car.thread.is_alive() for car in c.cars) and time.monotonic() < t0 + 40.0:
            for i, car in enumerate(c.cars):
                moved[i] = max(moved[i], car.vehicle.state().speed)
            time.sleep(0.05)
        wait_until(lambda: not any(car.thread.is_alive() for car in c.cars), 5.0, "runs ended")
        at_rest = [abs(car.vehicle.state().speed) < 0.1 for car in c.cars]
        armed = [car.vehicle.armed for car in c.cars]
    finally:
        c.stop()
    result: dict = {
        "exit_codes": [car.result.exit_code for car in c.cars],
        "reasons": [car.result.reason for car in c.cars],
        "lines": lines,
        "closed": closed,
        "at_rest": at_rest,
        "armed": armed,
        "top_speeds": moved,
        "tracebacks": [
            r.getMessage() for r in records if r.exc_info or "Traceback" in r.getMessage()
        ],
        "seconds": time.monotonic() - t0,
    }
    metas, rows, last_speed = [], [], []
    for i in range(2):
        metas.append(json.loads((run / f"vehicle_{i}.json").read_text()))
        log = read_log(run / f"vehicle_{i}.csv")  # a torn last line is skipped
        rows.append(int(len(log["t_s"])))
        last_speed.append(float(log["speed_mps"][-1]))
    result["metas"] = [
        {
            k: m.get(k)
            for k in ("exit_reason", "exit_code", "log_write_failed", "ticks", "autopilot")
        }
        for m in metas
    ]
    result["rows"] = rows
    result["last_logged_speed"] = last_speed
    return result


if __name__ == "__main__":
    try:
        res = main(Path(sys.argv[1]), int(sys.argv[2]))
    except Exception as exc:  # noqa: BLE001 - reported to the test
        import traceback

        res = {"error": f"{exc!r}", "trace": traceback.format_exc()}
    print(json.dumps(res))
