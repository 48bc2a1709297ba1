"""SIGTERM and ``openconvoy abort`` on real deploy processes, BSMs over real IPv6 multicast,
inside a private network namespace (never a real interface)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from openconvoy.comms.netns import netns_unavailable_reason, run_in_netns

DRIVER = Path(__file__).with_name("netns_deploy_driver.py")


def run_driver(action: str, out: Path) -> dict:
    reason = netns_unavailable_reason()
    assert reason is None, f"these tests need a private network namespace: {reason}"
    (r,) = run_in_netns([[sys.executable, str(DRIVER), action, str(out)]], timeout=90)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads(r.stdout.strip().splitlines()[-1])
    assert "error" not in result, (
        result,
        [p.read_text()[-2000:] for p in out.glob("deploy_*.txt")],
    )
    return result


def check_stopped_held_logged(result: dict, reason: str) -> None:
    assert result["exit_codes"] == [0, 0]
    assert result["reasons"] == [reason, reason]
    for events in result["events"]:
        events = [e for e in events if not e["reason"].startswith("control loop late")]
        assert events[0]["reason"] == reason
    for first in result["first_after"]:
        # the first setpoint after detection is a stop, within 0.5 s (or none was needed)
        assert first is None or (first[1] == 0.0 and first[0] <= 0.5)
    assert all(s == 0.0 for speeds in result["late_speeds"] for s in speeds)
    assert result["modes"] == ["HOLD", "HOLD"]
    assert all(abs(v) < 0.05 for v in result["speeds"])
    assert all(n > 20 for n in result["log_rows"])  # the logs survived


@pytest.mark.netns
def test_sigterm_stops_holds_flushes_and_exits_zero(tmp_path):
    check_stopped_held_logged(run_driver("sigterm", tmp_path), "SIGTERM")


@pytest.mark.netns
def test_openconvoy_abort_stops_the_whole_convoy(tmp_path):
    check_stopped_held_logged(run_driver("abort", tmp_path), "convoy abort")
