"""Forged leaders and aborts against three real deploy processes on simulated vehicles,
signed BSMs over real IPv6 multicast in a private network namespace (issue 12)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from openconvoy.comms.netns import netns_unavailable_reason, run_in_netns

DRIVER = Path(__file__).with_name("netns_auth_driver.py")


@pytest.mark.netns
@pytest.mark.e2e
def test_forgers_change_nothing_unsigned_abort_is_ignored_signed_abort_stops_all(tmp_path):
    reason = netns_unavailable_reason()
    assert reason is None, f"this test needs a private network namespace: {reason}"
    (r,) = run_in_netns([[sys.executable, str(DRIVER), str(tmp_path)]], timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "error" not in res, (res, [p.read_text()[-2000:] for p in tmp_path.glob("deploy_*.txt")])
    assert res["forger_rc"] == [0, 0], res["forger_err"]
    # every forged frame was counted as rejected by every vehicle: the keyless forger's
    # (and the unsigned abort's 3 datagrams) as unsigned, the foreign key's as bad certificate
    for rejected in res["rejected"]:
        assert rejected["unsigned"] == 200 + 3, rejected
        assert rejected["bad_certificate"] == 200, rejected
        assert rejected["bad_signature"] == rejected["wrong_sender"] == 0
    # ... and changed nothing: nobody sped towards the "leader" 1 km ahead or at 160 m/s
    assert res["max_follower_speed_during"] < 2.6, res
    assert res["metrics"]["min_gap_m"] >= 14.0, res["metrics"]
    assert res["metrics"]["collisions"] == 0
    # the unsigned abort was ignored, the signed one stopped every deploy: stop, HOLD, logs
    assert res["running_after_unsigned"] == [True, True, True]
    assert res["exit_codes"] == [0, 0, 0]
    assert res["reasons"] == ["convoy abort"] * 3, res
    assert res["modes"] == ["HOLD"] * 3
    assert all(abs(v) < 0.05 for v in res["final_speeds"])
    assert all(n > 100 for n in res["log_rows"])
