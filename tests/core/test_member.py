import math

import numpy as np
import pytest

from openconvoy.core.ladder import LadderConfig, acc_speed, rung
from openconvoy.core.member import ConvoyMember, MemberConfig
from openconvoy.core.observation import ObservationLayout
from openconvoy.core.state import VehicleState


def S(vid, t, x, y=0.0, v=1.0, h=0.0):
    return VehicleState(vid, t, x, y, v, h)


def member(vid=2, n=3, **kw):
    return ConvoyMember(vid, n, MemberConfig(**kw), lengths=[0.8] * n)


def test_leader_following_member_shows_the_policy_the_leader_only():
    """ρ = leader: the policy sees the leader alone; the predecessor's messages are kept
    for the braking rule all the same (issue 22, D47: before, they were dropped and the
    rule had no gap)."""
    m = member(topology="leader")
    m.observe_own(S(2, 0.0, 0.0))
    assert m.receive(S(0, 0.0, 30.0), 0.0)
    assert m.receive(S(1, 0.0, 15.0), 0.0)  # kept for the rule
    assert not m.receive(S(3, 0.0, -15.0), 0.0)  # the follower: filtered
    assert not m.receive(S(2, 0.0, 0.0), 0.0)  # own echo
    assert m.msgs_received == 2 and m.msgs_filtered == 2
    frame = m.sense(0.0)
    view = m.layout.view(frame.observation)
    assert view.states("pred_1")[0, 6] == 0.0  # vehicle 1 not in the observation
    assert view.states("pred_2")[0, 6] == 1.0  # vehicle 0 is pred_2 of vehicle 2
    assert frame.pred_gap is None  # nor in the degraded rung's ACC target
    gap, closing = m.gap_estimate(0.0)
    assert gap == pytest.approx(15.0) and closing == pytest.approx(0.0)


def test_observation_on_a_straight_road_at_the_desired_gaps():
    m = member()
    m.observe_own(S(2, 1.0, 0.0))
    m.receive(S(0, 0.9, 29.9), 1.0)
    m.receive(S(1, 0.9, 14.9), 1.0)
    obs = m.observation(1.0)
    view = m.layout.view(obs)
    p1 = view.target("pred_1")
    # Dead-reckoned 0.1 s at 1 m/s: exactly 15 m ahead along the path.
    assert p1["arc_gap"] == pytest.approx(15.0) and p1["spacing_error"] == pytest.approx(
        0.0, abs=1e-6
    )
    assert view.target("pred_2")["desired_gap"] == pytest.approx(30.0)
    assert view.target("leader")["valid"] == 0.0  # leader already is pred_2
    assert view.states("pred_1")[0, :2] == pytest.approx([14.9, 0.0])
    assert view.states("pred_1")[0, 5] == pytest.approx(0.1)  # age
    f = m.sense(1.0)
    assert (f.observation == obs).all()  # sensing twice gives the same
    assert f.desired_gap_m == 15.0 and f.spacing_error_m == pytest.approx(0.0, abs=1e-6)
    assert f.pred_msg_age_s == pytest.approx(0.1)
    assert obs.dtype == np.float32 and obs.shape == (m.layout.size,)


def test_path_features_in_the_ego_frame():
    m = member(vid=1, n=2)
    # Ego 1 m right of the predecessor's path, heading 0.1 rad left of it.
    m.observe_own(S(1, 0.0, 0.0, y=-1.0, h=0.1))
    for k in range(20):  # predecessor drove along y = 0
        m.receive(S(0, -2.0 + 0.1 * k, 5.0 + 0.5 * k), -2.0 + 0.1 * k)
    path = m.layout.view(m.observation(0.0)).path
    assert path["valid"] == 1.0
    assert path["cross_track"] == pytest.approx(1.0)  # path is to the left
    assert path["heading_error"] == pytest.approx(-0.1)
    assert path["la1_x"] > 0


def test_history_keeps_last_k_newest_first():
    m = member(vid=1, n=2, k=2)
    m.observe_own(S(1, 1.0, 0.0))
    for t in (0.1, 0.2, 0.3):
        m.receive(S(0, t, 15.0 + t), 1.0)
    states = m.layout.view(m.observation(1.0)).states("pred_1")
    assert states[:, 0] == pytest.approx([15.3, 15.2])


def test_ladder_rungs():
    cfg = LadderConfig(enabled=True, degrade_after_s=0.5, stop_after_s=2.0)
    assert [rung(a, cfg) for a in (0.0, 0.5, 0.51, 2.0, 2.01, math.inf)] == [
        "coop",
        "coop",
        "degraded",
        "degraded",
        "stop",
        "stop",
    ]
    assert rung(math.inf, LadderConfig(enabled=False)) == "coop"
    with pytest.raises(ValueError):
        LadderConfig(degrade_after_s=2.0, stop_after_s=1.0)


def test_acc_speed_widens_the_gap():
    cfg = LadderConfig(enabled=True, extra_headway_s=1.0, gap_gain=0.5)
    # At the desired gap + 1 s * 2 m/s, matching speed: hold 2 m/s.
    assert acc_speed(17.0, 0.0, 2.0, 15.0, cfg) == pytest.approx(2.0)
    # At the normal gap (2 m short of the wider one): slow down.
    assert acc_speed(15.0, 0.0, 2.0, 15.0, cfg) == pytest.approx(1.0)
    assert acc_speed(5.0, -2.0, 2.0, 15.0, cfg) == 0.0


def test_member_ladder_degrades_stops_and_recovers():
    m = ConvoyMember(
        1,
        2,
        MemberConfig(ladder=LadderConfig(enabled=True, degrade_after_s=0.5, stop_after_s=2.0)),
        lengths=[0.8, 0.8],
        decels=[1.0, 1.0],
    )
    m.observe_own(S(1, 0.0, 0.0, v=2.0))
    act = np.array([3.0, 0.1], dtype=np.float32)
    # Never heard: stop.
    f = m.sense(0.0)
    assert m.supervise(act, f)[1] == "stop"
    m.receive(S(0, 0.0, 15.0, v=2.0), 0.0)
    f = m.sense(0.3)
    a, mode = m.supervise(act, f)
    assert mode == "coop" and a[0] == pytest.approx(3.0)
    m.observe_own(S(1, 1.0, 0.0, v=2.0))
    f = m.sense(1.0)
    a, mode = m.supervise(act, f)
    # Degraded: ACC on the predecessor dead-reckoned as braking at 1 m/s² since its
    # message 1 s ago (1.5 m on, 1 m/s): 16.5 m ahead, wanted 15 + 2 = 17 m.
    assert (
        mode == "degraded"
        and a[0] == pytest.approx(1.0 + 0.5 * (16.5 - 17.0))
        and a[1] == pytest.approx(0.1)
    )
    # A ranging sensor reading takes precedence over the estimate.
    a, _ = m.supervise(act, f, ranging=(17.0, 0.0))
    assert a[0] == pytest.approx(2.0)
    f = m.sense(2.5)
    a, mode = m.supervise(act, f)
    assert mode == "stop" and a[0] == 0.0 and a[1] == 0.0
    m.receive(S(0, 2.6, 20.0, v=2.0), 2.6)
    f = m.sense(2.6)
    assert m.supervise(act, f)[1] == "coop"


def test_layout_sizes_and_mismatch_message():
    lay = ObservationLayout(M=2, k=3)
    assert lay.slots == ("leader", "pred_1", "pred_2", "follower")
    assert lay.size == 4 * 3 * 7 + 3 + 3 * 5 + 9
    with pytest.raises(ValueError, match="M 3 vs 2"):
        lay.check_compatible({"version": 1, "M": 3, "k": 3, "size": 0})
    lay.check_compatible(lay.describe())


def test_dead_reckoning_is_bounded_and_old_targets_are_dropped():
    # Issue 10, row 1: a dead leader once "drove on" at 2 m/s forever, valid.
    ladder = LadderConfig(degrade_after_s=0.5, stop_after_s=2.0)  # off: the ages still hold
    m = ConvoyMember(1, 2, MemberConfig(ladder=ladder), lengths=[0.8, 0.8], decels=[1.0, 1.0])
    m.receive(S(0, 0.0, 15.0, v=2.0), 0.0)
    m.observe_own(S(1, 0.4, 0.0, v=2.0))
    est = m.estimate(0, 0.4)
    assert (est.x, est.speed, est.stale) == (pytest.approx(15.8), 2.0, False)  # constant speed
    est = m.estimate(0, 1.5)  # stale: as if braking at 1 m/s² since the message
    assert (est.x, est.speed, est.stale) == (
        pytest.approx(15.0 + 3.0 - 1.125),
        pytest.approx(0.5),
        True,
    )
    assert m.estimate(0, 2.0).x == pytest.approx(17.0)  # stopped after 2 m
    assert m.estimate(0, 2.01) is None  # older than the stop age: no target at all
    m.observe_own(S(1, 2.01, 0.0, v=2.0))
    view = m.layout.view(m.observation(2.01))
    assert view.target("pred_1")["valid"] == 0.0 and view.valid_targets() == []
    assert view.states("pred_1")[0, 5] == pytest.approx(2.01)  # the state slot keeps its age
    # The braking rule's gap does not expire: the sender is still no further than braking
    # at its limit took it (stopped at 17 m), and the ego closes on it at 2 m/s.
    assert m.gap_estimate(2.01) == (pytest.approx(17.0), pytest.approx(2.0))
    assert m.gap_estimate(60.0) == m.gap_estimate(2.01)
    # Without a braking limit a silent sender is taken to have stopped where last heard.
    m2 = member(vid=1, n=2)
    m2.receive(S(0, 0.0, 15.0, v=2.0), 0.0)
    m2.observe_own(S(1, 1.0, 0.0, v=2.0))
    assert m2.estimate(0, 1.0).x == 15.0 and m2.gap_estimate(1.0) == (15.0, 2.0)


def test_ladder_watches_every_needed_target_not_only_the_nearest():
    # Issue 10, row 1: the ladder watched only the nearest predecessor, so follower 2
    # cooperated on with a dead leader.
    lad = LadderConfig(enabled=True, degrade_after_s=0.5, stop_after_s=2.0)
    m = ConvoyMember(2, 3, MemberConfig(ladder=lad), lengths=[0.8] * 3)
    m.receive(S(0, 0.0, 30.0), 0.0)  # the leader, then silence
    for k in range(31):
        m.receive(S(1, 0.1 * k, 15.0 + 0.1 * k), 0.1 * k)
    m.observe_own(S(2, 3.0, 3.0))
    f = m.sense(3.0)
    assert m.needed_age(3.0) == pytest.approx(3.0)
    _, mode = m.supervise(np.array([1.0, 0.0], dtype=np.float32), f)
    assert mode == "stop"
