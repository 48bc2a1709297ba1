"""Failsafe and envelope rules as pure logic, with time injected (bridge.failsafes)."""

from __future__ import annotations

import math

import pytest

from openconvoy.bridge.failsafes import (
    DRIVE,
    SILENT,
    STOP,
    Envelope,
    Failsafes,
    LinkWatchdog,
    LoopTimer,
    TickInputs,
)
from openconvoy.core.safety import BrakingGap, for_vehicle


def fresh(now: float, **kw) -> TickInputs:
    """Inputs of a healthy tick at ``now``: telemetry 10 ms old, heartbeat 0.2 s old."""
    base = dict(now=now, t_telemetry=now - 0.01, t_heartbeat=now - 0.2, speed_cmd=1.0)
    base.update(kw)
    return TickInputs(**base)


def test_watchdog_telemetry_silence_half_second():
    w = LinkWatchdog(0.5, 3.0)
    assert w.update(10.0, 9.6, 9.0) == "ok"
    assert w.update(10.0, 9.5, 9.0) == "ok"  # exactly 0.5 s: still fresh
    assert w.update(10.01, 9.5, 9.0) == "lost"
    assert w.t_lost == pytest.approx(10.01)
    assert w.update(10.5, 10.49, 10.4) == "returned"
    assert w.update(20.0, 19.99, 19.9) == "returned"  # a loss is remembered for the run


def test_watchdog_heartbeat_three_seconds_and_closed_link():
    w = LinkWatchdog(0.5, 3.0)
    assert w.update(10.0, 9.99, 7.0) == "ok"
    assert w.update(10.0, 9.99, 6.99) == "lost"
    w2 = LinkWatchdog()
    assert w2.update(1.0, 1.0, 1.0, open_=False) == "lost"


def test_healthy_tick_drives():
    f = Failsafes()
    v = f.decide(fresh(1.0))
    assert v.command == DRIVE and not v.hold and not v.exit and not v.failsafe


def test_link_loss_stops_then_holds_when_it_returns_and_stays_held():
    f = Failsafes()
    assert f.decide(fresh(1.0)).command == DRIVE
    v = f.decide(fresh(1.6, t_telemetry=1.0))
    assert (v.command, v.hold, v.failsafe) == (STOP, False, True)
    assert f.events == [(1.6, "autopilot link lost")]
    v = f.decide(fresh(2.0))  # telemetry back: HOLD, keep commanding a stop until held
    assert (v.command, v.hold) == (STOP, True)
    v = f.decide(fresh(2.1, held=True))
    assert v.command == SILENT and v.failsafe
    assert f.decide(fresh(9.0, held=True)).command == SILENT  # never drives again by itself


def test_pilot_takeover_latches_silence():
    f = Failsafes()
    v = f.decide(fresh(1.0, pilot_took_over=True))
    assert (v.command, v.failsafe) == (SILENT, True)
    # Even if the link stopped reporting it, we never take the vehicle back.
    assert f.decide(fresh(2.0)).command == SILENT
    assert not f.decide(fresh(3.0)).hold


@pytest.mark.parametrize("kw", [dict(stop_requested="SIGTERM"), dict(abort=True)])
def test_signal_and_abort_stop_hold_and_exit(kw):
    f = Failsafes()
    v = f.decide(fresh(1.0, **kw))
    assert (v.command, v.hold, v.exit, v.failsafe) == (STOP, True, True, True)
    assert f.decide(fresh(1.05)).exit  # latched


def test_geofence_now_and_predicted():
    env = Envelope(geofence_radius_m=10.0, geofence_lookahead_s=1.0)
    assert not env.outside_fence(8.0, 0.0, 0.0, 1.0)
    assert env.outside_fence(9.5, 0.0, 0.0, 1.0)  # would be at 10.5 m in 1 s
    assert not env.outside_fence(9.5, 0.0, math.pi, 1.0)  # heading back inside
    assert env.outside_fence(0.0, 10.1, 0.0, 0.0)
    f = Failsafes(envelope=env)
    assert f.decide(fresh(1.0, x=5.0)).command == DRIVE
    v = f.decide(fresh(1.05, x=9.5))
    assert (v.command, v.hold, v.reason) == (STOP, True, "geofence")
    assert f.decide(fresh(1.1, x=0.0)).command == STOP  # latched: a person decides


def test_min_gap_emergency_stop():
    f = Failsafes(envelope=Envelope(min_gap_m=1.0))
    assert f.decide(fresh(1.0, gap_m=1.01)).command == DRIVE
    assert f.decide(fresh(1.0, gap_m=math.nan)).command == DRIVE  # unknown gap: no rule
    v = f.decide(fresh(1.05, gap_m=0.99))
    assert (v.command, v.hold, v.failsafe) == (STOP, True, True)
    assert v.reason.startswith("gap 0.99 m")


def test_policy_error_stops_without_hold_and_counts():
    f = Failsafes()
    v = f.decide(fresh(1.0, policy_error="ValueError: boom"))
    assert (v.command, v.hold, v.failsafe) == (STOP, False, True)
    assert f.decide(fresh(1.05)).command == STOP
    f.decide(fresh(1.1, policy_error="ValueError: boom"))
    assert f.policy_errors == 2


def test_stale_messages_stop_and_hold_for_good():
    # Issue 10: a stop for stale messages once left the vehicle in GUIDED without HOLD,
    # and fresh messages drove it off again.
    f = Failsafes(envelope=Envelope(max_msg_age_s=3.0))
    assert f.decide(fresh(1.0, needed_age_s=2.9)).command == DRIVE
    v = f.decide(fresh(1.05, needed_age_s=3.1))
    assert (v.command, v.hold, v.failsafe, v.reason) == (
        STOP,
        True,
        True,
        "messages needed are stale",
    )
    assert f.decide(fresh(1.1, needed_age_s=0.1)).command == STOP  # latched
    assert f.decide(fresh(1.15, needed_age_s=0.1, held=True)).command == SILENT  # held: quiet


def test_ladder_stop_holds():
    f = Failsafes()
    assert f.decide(fresh(1.0)).command == DRIVE
    v = f.decide(fresh(1.05, stale_stop=True))
    assert (v.command, v.hold, v.reason) == (STOP, True, "staleness ladder stop")
    assert f.decide(fresh(1.1)).hold  # fresh messages do not undo it
    assert f.events == [(1.05, "staleness ladder stop")]


def test_braking_aware_gap_stops_before_the_bumpers_meet():
    # 1/6 car behind a 1/10 car: 0.874 m of half lengths; brakes at 1 m/s² after 0.17 s
    # (0.12 s delay, a 20 Hz control period) through a 0.35 s lag (saturated above
    # 0.35 m/s: + a·τ²/2 = 0.061 m).
    rule = for_vehicle(1.0, 0.12, 0.35, 0.97)
    assert rule.margin_m == pytest.approx(0.2425)
    env = Envelope(min_gap_m=1.0, braking=rule, ego_length_m=0.97, pred_length_m=0.779)
    # The old rule's 1 m centre to centre is 0.13 m between bumpers: now far too close.
    assert env.too_close(1.0, 0.0).startswith("gap 0.13 m between bumpers")
    # Closing at 2 m/s (own speed unknown: the vehicle ahead taken as at rest) needs 2 m
    # of braking + 0.34 m of reaction + 0.061 m of lag: 4.2 m centre gap fires.
    assert env.too_close(0.874 + 2.0 + 0.34 + 0.061 + 0.24, 2.0)
    assert env.too_close(0.874 + 2.0 + 0.34 + 0.061 + 0.245, 2.0) == ""
    assert env.too_close(0.874 + 0.25, 0.0) == ""
    assert env.too_close(0.874 + 0.25, -3.0) == ""  # opening: only the margin counts
    assert env.too_close(math.nan, 2.0) == ""
    f = Failsafes(envelope=env)
    v = f.decide(fresh(1.0, gap_m=3.3, closing_mps=2.0))
    assert (v.command, v.hold) == (STOP, True) and "after braking" in v.reason


@pytest.mark.parametrize(
    "bad",
    [dict(decel_mps2=0.0), dict(reaction_s=-1.0), dict(margin_m=math.nan), dict(margin_m=math.inf)],
)
def test_braking_gap_rejects_bad_numbers(bad):
    kw = dict(decel_mps2=1.0, reaction_s=0.5, margin_m=0.2) | bad
    with pytest.raises(ValueError, match="braking gap"):
        BrakingGap(**kw)


def test_speed_cap():
    env = Envelope(speed_cap_mps=2.0)
    assert env.cap(5.0) == 2.0
    assert env.cap(-1.0) == 0.0
    assert env.cap(math.nan) == 0.0
    assert env.cap(1.5) == 1.5


def test_priority_takeover_over_everything():
    f = Failsafes(envelope=Envelope(min_gap_m=1.0))
    v = f.decide(fresh(1.0, pilot_took_over=True, abort=True, gap_m=0.1, t_telemetry=0.0))
    assert v.command == SILENT  # the person has the vehicle; we send nothing at all


def test_loop_timer_counts_overruns_and_skips_missed_slots():
    t = LoopTimer(0.05, start=0.0)
    t.begin(0.0)
    assert t.wait_time(0.01) == pytest.approx(0.04)
    t.begin(0.05)
    assert t.begin(0.23) == pytest.approx(0.13)  # slots 0.10 and 0.15 passed without a tick
    assert t.overruns == 2 and t.late_ticks == 1  # and 0.13 s is more than 2 periods late
    assert t.next_tick == pytest.approx(0.25)  # the schedule skips, no burst
    t.begin(0.25)
    t.begin(0.36)  # 0.06 s late: one slot missed, not late enough to be a failsafe
    assert t.overruns == 3 and t.late_ticks == 1 and t.ticks == 5
    t.begin(0.40 + 3.7)  # a 3.7 s stall at 20 Hz misses 74 slots, not 1
    assert t.overruns == 3 + 74 and t.late_ticks == 2
    with pytest.raises(ValueError):
        LoopTimer(0.0, start=0.0)


def test_a_tick_over_two_periods_late_stops_and_is_one_event_per_episode():
    f = Failsafes()
    assert f.decide(fresh(1.0, late_periods=1.9)).command == DRIVE
    v = f.decide(fresh(1.05, late_periods=2.5))
    assert (v.command, v.failsafe, v.reason) == (STOP, True, "control loop late")
    assert f.decide(fresh(1.1, late_periods=30.0)).command == STOP
    assert f.decide(fresh(1.15)).command == DRIVE  # on time again: not latched
    f.decide(fresh(2.0, late_periods=3.0))
    assert [r for _, r in f.events] == [
        "control loop late (2.5 periods)",
        "control loop late (3.0 periods)",
    ]


def test_signal_after_takeover_ends_the_run_without_commanding():
    f = Failsafes()
    f.decide(fresh(1.0, pilot_took_over=True))
    v = f.decide(fresh(2.0, stop_requested="SIGTERM"))
    assert (v.command, v.exit, v.hold) == (SILENT, True, False)
