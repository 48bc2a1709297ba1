"""Issue 22, item 1: the emergency rule brakes for whatever is ahead, in every topology.

Each run below collided at aea1a73 (numbers from the project's defect list defects-aea1a73.md, D47-D49, and
re-measured there): D47 ``platoon-leader`` kept nothing of the vehicle directly ahead;
D48 the rule took the predecessor as holding its speed; D49 the scenario leader lapped
into stopped followers on the closed track.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.core.safety import BrakingGap, for_vehicle, gap_reduction_m
from openconvoy.experiments.runs import RunConfig, run_sim


def _min_clearance_to_leader(log: dict, lengths: dict[int, float]) -> float:
    """Smallest gap between bumpers (m, centre gap less half lengths) from the leader to
    any follower over the run: the lapping leader's, which the pair metrics miss."""
    vid, t = np.asarray(log["vehicle_id"]), np.asarray(log["t_s"])
    x, y = np.asarray(log["x_m"], dtype=float), np.asarray(log["y_m"], dtype=float)
    lead = vid == 0
    worst = math.inf
    for j in sorted(set(vid.tolist()) - {0}):
        mine = vid == j
        assert np.array_equal(t[lead], t[mine])
        d = np.hypot(x[lead] - x[mine], y[lead] - y[mine]) - 0.5 * (lengths[0] + lengths[j])
        worst = min(worst, float(d.min()))
    return worst


def test_rule_assumes_the_vehicle_ahead_may_brake_d48_numbers() -> None:
    """D48's moment: follower 2 at 20.7 m/s, 12.45 m (centre) behind vehicle 1 at 14.9
    m/s, full-size cars (4.8 m). The old rule (closing speed only: 5.8²/16 + 0.55·5.8)
    left 2.35 m > the 1.2 m margin and did not fire; braking at the limit from 14.9 m/s
    the predecessor stops 13.9 m on, the follower needs 31.6 m: 17.7 m more."""
    rule = for_vehicle(8.0, 0.15, 0.4, 4.8)  # reaction 0.15 s + a 0.05 s control period
    bumper = 12.45 - 4.8
    old = BrakingGap(8.0, 0.55, rule.margin_m)  # the old rule: closing speed, reaction + lag
    assert old.clearance(bumper, 5.8) == pytest.approx(2.35, abs=0.01)
    assert not old.too_close(bumper, 5.8)
    assert rule.stopping_distance(5.8, 20.7, 8.0) == pytest.approx(
        20.7 * 0.2 + 20.7**2 / 16 + 0.5 * 8.0 * 0.4**2 - 14.9**2 / 16
    )
    assert rule.too_close(bumper, 5.8, 20.7, 8.0)
    assert rule.clearance(bumper, 5.8, 20.7, 8.0) < -8.0


def test_reduction_at_rest_equal_speeds_and_a_harder_braking_ego() -> None:
    # At rest nothing shrinks; at equal speeds and limits only the delay and the lag's tail.
    assert gap_reduction_m(0.0, 0.0, 0.15, 0.4, 8.0, 8.0) == 0.0
    assert gap_reduction_m(25.0, 25.0, 0.15, 0.4, 8.0, 8.0) == pytest.approx(
        25.0 * 0.15 + 0.5 * 8.0 * 0.4 * 0.4
    )
    # Below the lag's knee (a·τ = 0.35 m/s) the speed decays: v·τ.
    assert gap_reduction_m(0.3, 0.0, 0.12, 0.35, 1.0, 1.0) == pytest.approx(0.3 * 0.12 + 0.3 * 0.35)
    # Speeding up, it goes on through the reaction: braking starts from 2.1 m/s.
    assert gap_reduction_m(2.0, 2.0, 0.1, 0.0, 1.0, 1.0, 1.0) == pytest.approx(
        2.0 * 0.1 + 0.5 * 0.1 * 0.1 + (2.1**2 - 2.0**2) / 2.0
    )
    assert gap_reduction_m(2.0, 2.0, 0.1, 0.0, 1.0, 1.0, -1.0) == pytest.approx(0.2)
    # A wall ahead (unknown braking limit): the ego's whole stopping distance.
    assert gap_reduction_m(10.0, 10.0, 0.0, 0.0, 5.0, math.inf) == pytest.approx(10.0)
    # The ego brakes harder than the vehicle ahead: the gap is smallest where the speeds
    # meet (1 s of reaction at 10 m/s, then 10 m/s² against 2 m/s² from 10 m/s).
    mid = gap_reduction_m(10.0, 10.0, 1.0, 0.0, 10.0, 2.0)
    ends = 10.0 + 100.0 / 20.0 - 100.0 / 4.0
    assert ends < 0.0 < mid
    ts = 10.0 / 8.0  # 10 - 10 (t - 1) = 10 - 2 t
    assert mid == pytest.approx((10.0 * ts - 5.0 * (ts - 1.0) ** 2) - (10.0 * ts - ts * ts))


@pytest.mark.parametrize(
    ("config", "old"),
    [
        # D47: collisions 1, min gap 0.83 m at aea1a73
        (RunConfig(policy="platoon-leader", faults=("halt:1@10",), seed=0), 0.83),
        # D47: follower 2 rammed vehicle 1's emergency stop at ~24 m/s
        (RunConfig(scenario="emergency-braking", policy="platoon-leader", per=0.6, seed=0), None),
        # D48: collisions 1, min gap 4.76 m (the cars are 4.8 m long)
        (
            RunConfig(
                scenario="emergency-braking",
                policy="cacc-lookahead1",
                per=0.6,
                faults=("dead:0@3",),
                seed=1,
            ),
            4.76,
        ),
    ],
    ids=["d47-halt", "d47-emergency-braking", "d48-dead-leader"],
)
def test_d47_d48_runs_that_collided_stop_short(config: RunConfig, old: float | None) -> None:
    r = run_sim(config)
    assert r.metrics["collisions"] == 0
    stops = [e for e in r.events if e["reason"].startswith("emergency stop")]
    assert stops, "the rule acted"
    if old is not None:
        assert r.metrics["min_gap_m"] > old


@pytest.mark.parametrize("fault", ["halt:1@10", "silent:0@10", "dead:1@10"])
def test_d49_the_track_leader_stops_for_the_convoy_in_its_path(fault: str) -> None:
    """At aea1a73 the leader passed 0.03 m from the stopped follower 2 at 79.4 s
    (``halt:1@10``; every policy and fault on ``track`` alike)."""
    r = run_sim(RunConfig(scenario="track", policy="paper", faults=(fault,), seed=0))
    lengths = {0: 0.779, 1: 0.97, 2: 0.779}
    assert r.metrics["collisions"] == 0
    (stop,) = [e for e in r.events if e["vehicle_id"] == 0 and "emergency stop" in e["reason"]]
    assert 60.0 < stop["t_s"] < 90.0
    # It stopped short of the tail, its 0.19 m margin kept to within a tick's travel.
    assert _min_clearance_to_leader(r.log, lengths) > 0.1


def test_the_runners_leader_gap_is_the_member_in_its_path() -> None:
    """``deploy`` (``bridge.runner.gap_ahead``) for vehicle 0: NaN at aea1a73, so
    ``deploy --track`` had only the speed cap and the geofence (D49)."""
    from openconvoy.bridge.runner import gap_ahead
    from openconvoy.core.member import ConvoyMember, MemberConfig
    from openconvoy.core.state import VehicleState

    member = ConvoyMember(0, 3, MemberConfig(), [0.8, 1.0, 0.8], [1.0, 1.0, 1.0])
    member.observe_own(VehicleState(0, 10.0, 0.0, 0.0, 1.5, 0.0))
    assert math.isnan(gap_ahead(member, 10.0)[0])  # nobody heard
    member.receive(VehicleState(1, 10.0, -15.0, 0.0, 0.0, 0.0), 10.0)  # behind: not in its path
    member.receive(VehicleState(2, 10.0, 3.0, 0.4, 0.0, math.pi), 10.0)  # the tail, ahead
    gap, closing = gap_ahead(member, 10.0)
    assert gap == pytest.approx(math.hypot(3.0, 0.4)) and closing == pytest.approx(1.5 * 3.0 / gap)
    member.receive(VehicleState(2, 10.1, 3.0, 5.0, 0.0, math.pi), 10.1)  # beside, 5 m off
    assert math.isnan(gap_ahead(member, 10.1)[0])
