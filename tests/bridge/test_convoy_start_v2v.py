"""The deploy runner with a real, signed V2V link (``comms.v2v.V2V`` on a memory transport,
real ECDSA): the convoy start refuses a leader whose clock is off or who does not sign
(D50, D46), a leader that starts without a member says who and since when (D61), and a
follower ends with exit 0 when the leader says it completed its scenario (D62)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "comms"))

from auth_testdata import T0, creds  # noqa: E402

from openconvoy.bridge.convoystart import ConvoyStart  # noqa: E402
from openconvoy.bridge.runner import DeployRunner, RunnerOptions  # noqa: E402
from openconvoy.comms.geodesy import Origin  # noqa: E402
from openconvoy.comms.multicast import MemoryBus  # noqa: E402
from openconvoy.comms.security.auth import Authenticator  # noqa: E402
from openconvoy.comms.tempids import TempIds  # noqa: E402
from openconvoy.comms.v2v import V2V, LinkConfig  # noqa: E402
from openconvoy.convoy import ConvoyConfig  # noqa: E402
from openconvoy.core.state import VehicleState  # noqa: E402
from openconvoy.policies import load_policy  # noqa: E402
from openconvoy.testing import FakeClock, FakeLink  # noqa: E402


class NowClock(FakeClock):
    """``FakeClock`` whose wall clock is near now (the test certificates' validity)."""

    def wall(self) -> float:
        return T0 + self.t


class ScriptedLeader:
    """The follower's V2V endpoint; before each poll the leader (a real signed ``V2V`` on
    the same bus) broadcasts its state at the follower's wall time plus ``offset_s`` (its
    clock), and from ``complete_at`` on its completion instead."""

    def __init__(self, clock: FakeClock, follower: V2V, leader: V2V, offset_s: float = 0.0,
                 complete_at: float = float("inf")) -> None:  # fmt: skip
        self.clock, self.follower, self.leader = clock, follower, leader
        self.offset_s, self.complete_at = offset_s, complete_at
        self.completed = False

    def __getattr__(self, name: str) -> Any:
        return getattr(self.follower, name)

    def poll(self, now: float, budget_s: float | None = None) -> list[Any]:
        t = now + self.offset_s
        if t >= self.complete_at:
            if not self.completed:
                self.leader.send_complete(t)
                self.completed = True
        else:
            self.leader.send(VehicleState(0, t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.8, 0.3), t)
        return self.follower.poll(now, budget_s)


def _follower(tmp_path, *, signed_leader=True, offset_s=0.0, complete_after_s=float("inf")):
    clock = NowClock()
    convoy = ConvoyConfig(name="lab", vehicles=("1/10", "1/10"))
    origin = Origin(*convoy.origin)
    ids = TempIds("lab", 2)
    bus = MemoryBus()
    leader = V2V(LinkConfig("mem"), ids, origin, 0, transport=bus.endpoint("0"),
                 auth=Authenticator(creds(0)) if signed_leader else None)  # fmt: skip
    own = V2V(LinkConfig("mem"), ids, origin, 1, transport=bus.endpoint("1"),
              auth=Authenticator(creds(1)))  # fmt: skip
    v2v = ScriptedLeader(clock, own, leader, offset_s, clock.wall() + complete_after_s)
    lines: list[str] = []
    link = FakeLink(clock, origin, 1, x=-15.0, y=0.0, move=False)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=1, duration_s=30.0, status_period_s=0),
        convoy,
        load_policy("paper"),
        link,
        v2v,
        clock=clock,
        sleep=clock.sleep,
        wall_clock=clock.wall,
        log_dir=tmp_path,
        on_status=lines.append,
    )
    return runner, link, lines


def test_a_follower_ends_with_exit_0_when_the_leader_completes(tmp_path):
    runner, link, lines = _follower(tmp_path, complete_after_s=3.0)
    result = runner.run()
    assert result.reason == "the leader completed its scenario", lines
    assert result.exit_code == 0 and not runner.failsafes.latched
    assert 3.0 <= result.ticks / 20.0 <= 3.2  # at once, not after a staleness latch


def test_a_leader_clock_beyond_the_tolerance_refuses_the_start(tmp_path):
    runner, link, lines = _follower(tmp_path, offset_s=2.0)
    result = runner.run()
    assert result.exit_code == 1
    assert result.reason.startswith("convoy start refused: vehicle 1: vehicle 0's clock is 2.0")
    assert "s ahead of this vehicle's" in result.reason and "synchronise" in result.reason
    assert runner.start_gate.t_start is None
    assert all(s[1] == 0.0 for s in link.sent)  # never moved
    # within the tolerance it starts (and reads the leader's messages as fresh)
    runner, link, lines = _follower(tmp_path / "ok", offset_s=0.8, complete_after_s=1.0)
    assert runner.run().exit_code == 0 and runner.start_gate.t_start is not None


def test_an_unsigned_leader_refuses_the_start_of_a_signed_follower(tmp_path):
    runner, link, lines = _follower(tmp_path, signed_leader=False)
    result = runner.run()
    assert result.exit_code == 1 and runner.start_gate.t_start is None
    assert "vehicle 0 sends unsigned V2V messages while this vehicle requires" in result.reason
    assert any("disagrees about [v2v] auth" in ln for ln in lines)


def test_a_leader_starting_without_a_member_says_who_and_since_when():
    t = [100.0]
    lines: list[str] = []
    gate = ConvoyStart(0, 3, lambda j: True, leader_waits=True, wait_s=120.0,
                       clock=lambda: t[0], on_status=lines.append)  # fmt: skip
    wall0 = 1.8e9  # 2027-01-15 08:00:00 UTC
    assert gate.update(t[0], wall0, 100.0)  # waiting
    gate.heard_from(1)
    t[0] = 220.5
    assert not gate.update(t[0], wall0 + 120.5, 100.0)  # gave up waiting
    since = time.strftime("%H:%M:%S", time.gmtime(wall0))
    assert lines == [
        f"vehicle 0: no message from vehicle 2 since {since} UTC (120 s): starting anyway"
    ]


def test_a_long_wait_to_start_says_who_is_missing_every_10_s():
    t = [0.0]
    lines: list[str] = []
    gate = ConvoyStart(0, 3, lambda j: True, leader_waits=True, wait_s=120.0,
                       clock=lambda: t[0], on_status=lines.append)  # fmt: skip
    for now in (0.0, 2.9, 3.0, 5.0, 12.9, 13.0):
        t[0] = now
        assert gate.update(now, 1.8e9 + now, 0.0)
    assert lines == [
        "vehicle 0: waiting 3 s for vehicles 1, 2 to be heard before starting; starting "
        "anyway after 120 s",
        "vehicle 0: waiting 13 s for vehicles 1, 2 to be heard before starting; starting "
        "anyway after 120 s",
    ]
    follower = ConvoyStart(2, 3, lambda j: True, leader_waits=True, wait_s=120.0,
                           clock=lambda: t[0], on_status=lines.append)  # fmt: skip
    follower.heard_from(0)
    lines.clear()
    t[0] = 4.0
    assert follower.update(4.0, 1.8e9, 0.0)
    assert lines == ["vehicle 2: waiting 4 s for vehicle 1 to be heard before starting"]


def test_a_follower_of_a_leader_only_topology_waits_for_the_vehicle_ahead_too():
    """Its Rx gate keeps only the leader, but the braking rule reads the gap to the vehicle
    directly ahead: a follower that never heard it is stopped in simulation
    (``core.safety.verdict``'s BLIND), so on a vehicle it does not start before hearing it."""
    t = [0.0]
    follower = ConvoyStart(2, 3, lambda j: j == 0, leader_waits=True, wait_s=120.0,
                           clock=lambda: t[0])  # fmt: skip
    follower.heard_from(0)
    assert follower.waiting_for(0.0) == [1]
    assert follower.update(0.1, 1.8e9, 0.0)
    follower.heard_from(1)
    assert not follower.update(0.2, 1.8e9, 0.0) and follower.t_start == 0.2


def test_a_refusal_must_last_a_second_a_backlog_read_at_the_first_tick_does_not_refuse():
    """A deploy that started slowly reads its members' queued messages at its first tick,
    1.35 s old, and the V2V link names a clock that far behind; the fresh messages of the
    next ticks clear it: the vehicle waited, then starts (the PX4 demo at load 8-17). A
    reason that holds for 1 s refuses the start for good."""
    reasons = iter(["vehicle 2: vehicle 0's clock is 1.35 s behind"] * 3 + [""] * 100)
    gate = ConvoyStart(2, 3, lambda j: True, leader_waits=True, wait_s=120.0,
                       clock=lambda: 0.0, refusal=lambda: next(reasons))  # fmt: skip
    gate.heard.update({0, 1})
    assert gate.update(0.0, 1.8e9, 0.0) and gate.update(0.05, 1.8e9, 0.0)
    assert gate.update(0.10, 1.8e9, 0.0) and not gate.refused  # waiting, not refused
    assert not gate.update(0.15, 1.8e9, 0.0) and gate.t_start == 0.15  # started
    stuck = ConvoyStart(2, 3, lambda j: True, leader_waits=True, wait_s=120.0,
                        clock=lambda: 0.0, refusal=lambda: "clock 2 s ahead")  # fmt: skip
    stuck.heard.update({0, 1})
    for k in range(20):
        assert stuck.update(0.05 * k, 1.8e9, 0.0) and not stuck.refused
    assert stuck.update(1.0, 1.8e9, 0.0) and stuck.refused == "clock 2 s ahead"
    assert stuck.t_start is None
