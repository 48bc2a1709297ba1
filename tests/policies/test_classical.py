"""The classical policy with stale or missing targets (issue 10): they only slow it."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.core.member import ConvoyMember
from openconvoy.core.state import VehicleState
from openconvoy.policies import load_policy


def follower2(policy, msgs, now, own_x=0.0, own_v=2.0):
    """Follower 2 of 3 with the paper's member; ``msgs``: (vehicle, t, x, speed)."""
    m = ConvoyMember(2, 3, policy.member_config, lengths=[0.78, 0.97, 0.78], decels=[1.0] * 3)
    for vid, t, x, v in msgs:
        m.receive(VehicleState(vid, t, x, 0.0, v, 0.0), t)
    m.observe_own(VehicleState(2, now, own_x, 0.0, own_v, 0.0))
    return m.observation(now)


def speed(policy, obs) -> float:
    policy.reset()
    return float(policy.act(obs)[0])


def test_a_phantom_leader_no_longer_outweighs_a_stopped_predecessor():
    # Issue 10, row 1: follower 1 stopped 13 m ahead (2 m too close), the leader silent
    # for 1.5 s, once dead-reckoned 3 m ahead of where it was and averaged in: 2.1 m/s.
    p = load_policy("paper")
    msgs = [(0, 28.5, 40.0, 2.0), (1, 30.0, 13.0, 0.0)]
    assert speed(p, follower2(p, msgs, 30.0)) == 0.0
    # Even with a fresh leader far ahead (follower 1 halted): the nearest one caps.
    msgs = [(0, 30.0, 40.0, 2.0), (1, 30.0, 13.0, 0.0)]
    assert speed(p, follower2(p, msgs, 30.0)) == 0.0


def test_a_predecessor_heard_but_too_old_stops_the_follower():
    p = load_policy("paper")
    msgs = [(0, 30.0, 30.0, 2.0), (1, 27.5, 15.0, 2.0)]
    assert speed(p, follower2(p, msgs, 30.0)) == 0.0  # follower 1 silent 2.5 s
    msgs = [(0, 30.0, 30.0, 2.0), (1, 30.0, 15.0, 2.0)]
    assert speed(p, follower2(p, msgs, 30.0)) > 1.5  # both fresh: drive on


@settings(max_examples=60, deadline=None)
@given(
    age=st.floats(0.0, 3.0),
    lead_x=st.floats(20.0, 45.0),
    lead_v=st.floats(0.0, 3.0),
    pred_x=st.floats(5.0, 25.0),
    pred_v=st.floats(0.0, 3.0),
    own_v=st.floats(0.0, 3.0),
)
def test_a_stale_leader_never_makes_the_follower_faster_than_a_fresh_one(
    age, lead_x, lead_v, pred_x, pred_v, own_v
):
    p = load_policy("paper")
    now = 30.0
    fresh = follower2(p, [(0, now, lead_x, lead_v), (1, now, pred_x, pred_v)], now, own_v=own_v)
    # The same leader state, heard ``age`` s ago at the position it would have had then.
    old = follower2(
        p,
        [(0, now - age, lead_x - lead_v * age, lead_v), (1, now, pred_x, pred_v)],
        now,
        own_v=own_v,
    )
    assert speed(p, old) <= speed(p, fresh) + 1e-4
    assert np.isfinite(speed(p, old))
