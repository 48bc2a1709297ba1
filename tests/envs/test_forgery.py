"""``forge:ID@T`` in the simulator: a keyless forger claiming to be the leader, 1 km ahead.
With authentication (the default) every forged message is rejected and counted, and the
run is the run without the forger; with ``auth = "off"`` the followers chase it."""

from __future__ import annotations

import numpy as np
import pytest

from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import parse_fault
from openconvoy.experiments.runs import RunConfig, run_sim


def _run(**kw):
    return run_sim(RunConfig(duration_s=25.0, **kw))


def test_authenticated_members_reject_every_forgery_and_nothing_changes():
    clean = _run()
    attacked = _run(faults=("forge:0@5",))
    for col in ("x_m", "speed_mps", "gap_m", "cmd_speed_mps"):
        assert np.array_equal(clean.log[col], attacked.log[col], equal_nan=True), col
    rejected = {e["vehicle_id"]: e["reason"] for e in attacked.events if "forged" in e["reason"]}
    # one forgery per 20 Hz tick from t = 5 s to t = 25 s inclusive (401 ticks), to each follower
    assert rejected == {1: "rejected 401 forged messages", 2: "rejected 401 forged messages"}
    assert attacked.metrics["min_gap_m"] >= 14.0


def test_without_authentication_the_forged_leader_is_chased():
    clean = _run(auth="off")
    attacked = _run(auth="off", faults=("forge:0@5",))
    assert not any("forged" in e["reason"] for e in attacked.events)
    late = attacked.log["t_s"] > 10.0
    followers = attacked.log["vehicle_id"] > 0
    # They speed up after it (1.5x the clean run's speed before issue 22; the braking
    # rule now stops the chase sooner: about 1.45x) ...
    assert (
        attacked.log["speed_mps"][late & followers].max()
        > 1.3 * clean.log["speed_mps"][late & followers].max()
    )
    assert attacked.metrics["min_gap_m"] < clean.metrics["min_gap_m"] - 5.0
    # ... until the rule, which reads the vehicle ahead, stops them short of it.
    assert attacked.metrics["collisions"] == 0
    assert any(e["reason"].startswith("emergency stop") for e in attacked.events)


def test_forge_fault_syntax():
    f = parse_fault("forge:0@12.5")
    assert (f.kind, f.vehicle, f.t_s, f.forges, f.brakes, f.mutes) == (
        "forge",
        0,
        12.5,
        True,
        False,
        False,
    )
    with pytest.raises(ConfigError, match="auth must be"):
        RunConfig(auth="maybe")
