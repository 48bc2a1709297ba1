"""A full log disk (D54), for real: a small tmpfs mounted as the log directory in a
private mount namespace (``unshare -rm``), two deploy runners on simulated vehicles."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DRIVER = Path(__file__).with_name("diskfull_driver.py")


@pytest.mark.e2e
def test_a_full_log_disk_stops_the_vehicles_with_one_line_and_keeps_the_metadata(tmp_path):
    assert shutil.which("unshare"), "this test needs util-linux's unshare (user namespaces)"
    r = subprocess.run(
        ["unshare", "-rm", sys.executable, str(DRIVER), str(tmp_path), "96"],
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "error" not in res, res
    assert "Traceback" not in r.stderr and res["tracebacks"] == []
    for i in range(2):
        why = "log write failed (" + str(tmp_path / "run" / f"vehicle_{i}.csv")
        assert res["reasons"][i].startswith(why) and "No space left on device" in res["reasons"][i]
        assert res["exit_codes"][i] == 1
        # one line says what happened and what the deploy does about it
        said = [ln for ln in res["lines"][i] if "log write failed" in ln and "stopping" in ln]
        assert len(said) == 1 and "metadata is still written" in said[0]
        assert sum("log write failed" in ln for ln in res["lines"][i]) == 2  # + "stopped (...)"
        assert res["closed"][i] == ["v2v", "link"]  # both closers still ran
        assert res["at_rest"][i] and not res["armed"][i]
        meta = res["metas"][i]
        assert meta["exit_code"] == 1 and meta["autopilot"] == "ardupilot"
        assert meta["log_write_failed"].endswith("No space left on device")
        assert res["rows"][i] > 10
    assert max(res["top_speeds"]) > 0.5  # the convoy was driving when the disk filled
