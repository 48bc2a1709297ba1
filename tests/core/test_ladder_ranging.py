"""The ladder's ranging override: a cut-in (or a too-close target) is followed by ranging."""

from __future__ import annotations

import numpy as np
import pytest

from openconvoy.core.ladder import LadderConfig, ranging_override
from openconvoy.core.member import ConvoyMember, MemberConfig
from openconvoy.core.spacing import SpacingConfig
from openconvoy.core.state import VehicleState

ON = LadderConfig(enabled=True)


def test_ranging_override_rule() -> None:
    # The sensor agrees with V2V and the gap is as desired: cooperate.
    assert not ranging_override(21.5, 21.8, 21.8, ON)
    # Something 10 m ahead while the predecessor is 21.8 m ahead by V2V: a cut-in.
    assert ranging_override(10.0, 21.8, 21.8, ON)
    # The predecessor itself, but 4 m closer than desired: follow it by ranging too.
    assert ranging_override(17.5, 17.6, 21.8, ON)
    # Within the margin (3 m): no switch.
    assert not ranging_override(19.0, 21.8, 21.8, ON)
    # Never with the ladder off.
    assert not ranging_override(5.0, 21.8, 21.8, LadderConfig(enabled=False))


def _member() -> ConvoyMember:
    cfg = MemberConfig(spacing=SpacingConfig("constant-distance", distance_m=20.0), ladder=ON)
    m = ConvoyMember(1, 2, cfg, lengths=[4.8, 4.8])
    m.receive(VehicleState(0, 0.0, 20.0, 0.0, 25.0, 0.0), 0.0)
    m.observe_own(VehicleState(1, 0.0, 0.0, 0.0, 25.0, 0.0))
    return m


def test_member_follows_a_cut_in_by_ranging_and_returns_to_coop() -> None:
    act = np.array([26.0, 0.0], dtype=np.float32)
    m = _member()
    f = m.sense(0.0)
    # The sensor sees the predecessor: cooperative, the policy's action unchanged.
    a, mode = m.supervise(act, f, ranging=(20.0, 0.0))
    assert mode == "coop" and a[0] == pytest.approx(26.0)
    # A car 8 m ahead at the same speed: degraded ACC on it (8 m against 20 + 25 wanted).
    a, mode = m.supervise(act, f, ranging=(8.0, 0.0))
    assert mode == "degraded"
    assert a[0] == pytest.approx(25.0 + 0.5 * (8.0 - 45.0))
    # It left: the sensor sees the predecessor again, the member cooperates again.
    assert m.supervise(act, f, ranging=(20.1, 0.0))[1] == "coop"
    # Without a sensor nothing changes.
    assert m.supervise(act, f)[1] == "coop"
