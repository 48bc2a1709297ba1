"""The braking rule with a predecessor never heard (the leaderboard's emergency-braking
collisions, docs/leaderboard.md).

Each run below collided before ``core.safety.verdict``'s ``BLIND``: with the predecessor
unheard the rule had no gap and let the follower drive on the leader's messages alone,
into a predecessor braking at its limit (8 m/s², the full-size car's), found 2.6-3.8 m
short when its first message came (centre gaps 4.52-4.79 m against the cars' 4.8 m).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.core.safety import BLIND, CLEAR, TOO_CLOSE, for_vehicle, verdict
from openconvoy.experiments.runs import LossSection, RunConfig, run_sim

LENGTH_M = 4.8  # the full-size car's


def test_verdict_blind_without_a_reading() -> None:
    """No reading at all: brake (``BLIND``), whatever the numbers; with one, the rule."""
    rule = for_vehicle(8.0, 0.15, 0.4, LENGTH_M).numbers
    assert verdict(False, math.nan, 0.0, 25.0, 8.0, 0.0, rule) == BLIND
    assert verdict(False, 100.0, 0.0, 0.0, 8.0, 0.0, rule) == BLIND
    # 10.53 m between bumpers, 23.15 m/s behind 20.95 m/s: the first message of run 1.
    assert verdict(True, 10.53, 2.2, 23.15, 8.0, 3.0, rule) == TOO_CLOSE
    assert verdict(True, 100.0, 0.0, 25.0, 8.0, 0.0, rule) == CLEAR


def _policy(tmp_path: Path, base: str) -> str:
    """``base`` with the leaderboard's 40 m/s limit for emergency-braking, as a file."""
    path = tmp_path / f"{base}-eb.toml"
    path.write_text(f'[policy]\nname = "{base}-eb"\nbase = "{base}"\nspeed_limit_mps = 40.0\n')
    return str(path)


@pytest.mark.parametrize(
    ("base", "per", "seed", "model", "old_min_gap"),
    [
        ("paper", 0.8, 0, "bernoulli", 4.788),
        ("paper-mpc", 0.8, 6, "bernoulli", 4.781),
        ("paper", 0.6, 9, "gilbert-elliott", 4.525),
    ],
)
def test_leaderboard_collisions_are_gone(
    tmp_path: Path, base: str, per: float, seed: int, model: str, old_min_gap: float
) -> None:
    config = RunConfig(
        scenario="emergency-braking",
        policy=_policy(tmp_path, base),
        per=per,
        seed=seed,
        loss=LossSection(model=model),
    )
    r = run_sim(config)
    assert r.metrics["collisions"] == 0
    assert r.metrics["min_gap_m"] > old_min_gap + 1.5  # 6.6-15 m now
    # Until a follower first hears its predecessor it commands rest (mode stop).
    vid, age = np.asarray(r.log["vehicle_id"]), np.asarray(r.log["pred_msg_age_s"], dtype=float)
    cmd, mode = np.asarray(r.log["cmd_speed_mps"], dtype=float), np.asarray(r.log["mode"])
    blind = (vid > 0) & np.isnan(age)
    assert blind.any(), "a follower missed its predecessor's first messages"
    assert np.all(cmd[blind] == 0.0)
    assert set(mode[blind].tolist()) <= {"stop", "failsafe"}
