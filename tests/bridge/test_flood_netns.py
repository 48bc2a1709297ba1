"""A flood of valid foreign BSMs over real IPv6 multicast (inside a private network
namespace) against a real ``openconvoy deploy``: its loop keeps its 20 Hz.

Reproduces the stall of issue 10 ("What was found" 2): 40,000 BSMs/s from a foreign id
used to drop a deploy to 2-3 Hz with gaps up to 3.7 s (before the fix this run saw 3
ticks in 2.5 s, gaps of 1 s). Runs ``benchmarks/bench_flood.py`` in its cheap form: one
follower, 2.5 s of flood (the benchmark itself runs three vehicles for 10 s).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from openconvoy.comms.netns import netns_unavailable_reason

BENCH = Path(__file__).parents[2] / "benchmarks" / "bench_flood.py"


@pytest.mark.netns
def test_a_flood_of_foreign_bsms_does_not_stall_the_loop(tmp_path):
    reason = netns_unavailable_reason()
    assert reason is None, f"this test needs a private network namespace: {reason}"
    r = subprocess.run(
        [sys.executable, str(BENCH), "--vehicles", "1", "--flood-s", "2.5", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "error" not in res, (res, [p.read_text()[-2000:] for p in tmp_path.glob("deploy_*.txt")])
    (v,) = res["per_vehicle"].values()
    # The flood did happen and reached the deploy, which dropped it as foreign. (Its rate
    # is what the machine gives the sender: 40,000/s asked, ~30,000/s on 2 idle cores,
    # ~5,000/s on 2 cores at a load of 10.)
    assert res["flood_sent"] > 10_000, res
    # The receive buffer is small on purpose (what is read is at most ~0.1 s old), so on a
    # loaded machine the kernel drops part of the flood before the deploy sees it.
    assert v["filtered"] > 5_000, res
    # Slack for a loaded 2-core CI machine; on an idle one it is 100 % and 1.1 periods.
    assert v["ticks"] >= 0.75 * v["expected_ticks"], res
    assert v["on_time"] >= 0.5, res  # before the fix: 0 (3 ticks in 2.5 s)
    assert v["max_gap_periods"] <= 6.0, res  # before: 21 (1.04 s)
