"""The fakes of ``openconvoy.testing`` against the runner they stand in for: a deploy run
on a ``FakeClock`` and ``FakeLink`` (the API reference's example), the scripted and replayed
links, the recording wrapper."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.bridge.localv2v import LocalBus, LocalV2V
from openconvoy.bridge.runner import DeployRunner, RunnerOptions
from openconvoy.comms.geodesy import Origin
from openconvoy.convoy import ConvoyConfig
from openconvoy.core.state import VehicleState
from openconvoy.testing import (
    WALL0,
    FakeClock,
    FakeLink,
    FixedPolicy,
    RecordingLink,
    ReplayLink,
    ReplayV2V,
    ScriptedLink,
)


def test_a_fake_clock_moves_only_when_slept_on() -> None:
    clock = FakeClock()
    assert clock() == 100.0 and clock.wall() == WALL0 + 100.0
    clock.sleep(0.25)
    clock.sleep(-1.0)  # never backwards
    assert clock() == 100.25


def test_a_runner_drives_a_fake_link_on_a_fake_clock() -> None:
    """The API reference's example: 2 s at 20 Hz in no real time; the follower, told
    1 m/s straight ahead, ends 2 m further on (an ideal autopilot)."""
    clock = FakeClock()
    convoy = ConvoyConfig(name="t", vehicles=("1/10", "1/10"))
    link = FakeLink(clock, Origin(*convoy.origin), 1, x=-15.0, y=0.0)
    bus = LocalBus()
    leader = LocalV2V(bus)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, duration_s=2.0, status_period_s=0),
        convoy,
        FixedPolicy(1.0, 0.0),
        link,
        LocalV2V(bus),
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        on_status=lambda line: None,
    )
    leader.send(VehicleState(0, clock.wall(), 0.0, 0.0, 1.0, 0.0), clock.wall())
    result = runner.run()
    assert result.ticks == pytest.approx(40, abs=3)
    speeds = [s for _, s, _ in link.sent]
    assert max(speeds) == 1.0 and link.sent[-1][1] == 0.0  # drove, then stopped
    assert link.x == pytest.approx(-15.0 + sum(1 for s in speeds if s == 1.0) / 20.0, abs=0.06)
    assert not link.armed  # a completed run ends disarmed


def test_a_scripted_link_takes_over_freezes_refuses_and_brakes() -> None:
    clock = FakeClock()
    link = ScriptedLink(
        clock, Origin(28.6, -81.2), 1, 0.0, 0.0, takeover_at=102.0, freeze_at=101.0,
        range_m=4.0, range_rate=-0.5, decel=2.0, speed=3.0,
    )  # fmt: skip
    assert link.setpoints.send(0.0, 0.0)
    clock.sleep(0.5)
    tel = link.poll()
    assert tel.state.speed == pytest.approx(2.0)  # 3 m/s braking at 2 m/s² for 0.5 s
    assert (tel.range_m, tel.range_rate_mps) == (4.0, -0.5)
    clock.sleep(0.6)
    frozen = link.poll()
    clock.sleep(0.5)
    assert link.poll() is frozen and not link.modes.pilot_took_over
    clock.sleep(0.5)
    assert link.modes.pilot_took_over and not link.modes.failsafe_took_over
    assert "MANUAL" in link.modes.takeover_reason and not link.setpoints.send(1.0, 0.0)
    link.modes.hold()
    link.modes.disarm()
    assert link.hold_log == [(102.1, 0.0)] and link.disarms == 1


def test_a_replay_link_gives_the_state_set_and_replay_v2v_the_inbox() -> None:
    clock = [5.0]
    link = ReplayLink(clock)
    assert link.poll() is None
    link.state = VehicleState(1, 0.0, 3.0, 4.0, 1.5, 0.1)
    link.ranging = (6.0, 0.2)
    tel = link.poll()
    assert tel.state is link.state and tel.t_telemetry == 5.0 and tel.range_m == 6.0
    assert link.setpoints.send(1.0, 0.5) and link.sent == [(1.0, 0.5)]
    v2v = ReplayV2V()
    v2v.inbox.append(link.state)
    heard = v2v.poll(5.0)
    assert [h.state for h in heard] == [link.state] and not heard[0].abort
    assert v2v.poll(5.1) == [] and v2v.counters.received == 1


def test_a_recording_link_records_what_went_out_only() -> None:
    class Refusing:
        last = (0.0, 0.25)
        sent_ok = False

        def send(self, speed: float, heading: float) -> bool:
            return self.sent_ok

        def stop(self) -> bool:
            return True

    class Inner:
        setpoints = Refusing()
        modes = None
        sent_ok = True

    inner = Inner()
    link = RecordingLink(inner)
    assert not link.setpoints.send(1.0, 0.0) and link.sent == []
    inner.setpoints.sent_ok = True
    assert link.setpoints.send(2.0, 0.1)
    assert link.setpoints.stop()
    assert [s[1:] for s in link.sent] == [(2.0, 0.1), (0.0, 0.25)]
    assert link.sent_ok is True  # anything else is the inner link's
    assert link.after(math.inf) == [] and len(link.after(-math.inf)) == 2
    assert np.all(np.diff([s[0] for s in link.sent]) >= 0)
