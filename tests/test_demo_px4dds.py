"""``openconvoy demo --link px4-dds --autopilot px4``: the three-vehicle demo through PX4 DDS
stand-ins (real Cyclone DDS on the namespace's loopback) against the MAVLink demo of the
same PX4 vehicles, scenario and seed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from openconvoy.comms.netns import netns_unavailable_reason

DURATION_S = 30.0


def _demo(out: Path, *extra: str) -> dict:
    r = subprocess.run(
        [sys.executable, "-m", "openconvoy.cli", "demo", "--json", "--autopilot", "px4"]
        + ["--duration", str(DURATION_S), "--out", str(out), *extra],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if r.returncode != 0:
        tails = [
            f"--- {f.name}\n" + "\n".join(f.read_text(errors="replace").splitlines()[-15:])
            for f in sorted(out.glob("deploy_*.txt"))
        ]
        raise AssertionError("\n".join([r.stdout[-3000:], r.stderr[-3000:], *tails]))
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.e2e
@pytest.mark.netns
def test_px4dds_demo_matches_the_mavlink_demo(tmp_path: Path) -> None:
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    dds = _demo(tmp_path / "dds", "--link", "px4-dds")
    mav = _demo(tmp_path / "mavlink")
    p95_dds = dds["deploy"]["p95_platooning_error_m"]
    p95_mav = mav["deploy"]["p95_platooning_error_m"]
    assert abs(p95_dds - p95_mav) <= 0.10 * p95_mav, (p95_dds, p95_mav)
    assert dds["deploy"]["collisions"] == 0 and dds["deploy"]["min_gap_m"] > 13.0
    for vid in range(3):
        meta = json.loads((tmp_path / "dds" / "deploy" / f"vehicle_{vid}.json").read_text())
        assert meta["link"] == f"px4-dds (domain 0, ns vehicle_{vid})"
        assert meta["autopilot"] == "px4"
        assert meta["overruns"] <= meta["ticks"] * 0.05
