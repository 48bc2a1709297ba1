"""The telemetry intake's mapping of the vehicle's boot clock onto the wall clock."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from openconvoy.bridge.mavlink.ranging import RangeIntake
from openconvoy.bridge.mavlink.telemetry import BootClockOffset, TelemetryIntake
from openconvoy.comms.geodesy import Origin


def _stamps(ratio: float, seconds: float, seed: int = 0):
    """(wall s, boot s, true measurement wall time s) of a 50 Hz stream from a vehicle whose
    clock runs at ``ratio`` of real time, each received 1-25 ms after it was measured."""
    rng = np.random.default_rng(seed)
    for k in range(int(seconds * 50)):
        measured = 100.0 + 0.02 * k
        yield measured + rng.uniform(0.001, 0.025), ratio * (measured - 100.0) + 5.0, measured


def test_a_slow_vehicle_clock_is_followed() -> None:
    """PX4 SIH's clock at 0.990 of real time: the offset grows 10 ms/s; the mapped
    measurement time stays within the transport latency of the truth over a minute (the
    old fixed 1 ms/s creep fell 9 ms/s behind: 0.54 s at 60 s)."""
    clock = BootClockOffset()
    errors = []
    for wall, boot, measured in _stamps(0.990, 60.0):
        assert not clock.observe(wall, boot)
        errors.append(boot + clock.offset(wall) - measured)
    late = np.abs(errors[-500:])
    assert late.max() < 0.005, late.max()
    assert abs(clock.drift() - 0.0101) < 0.0005, clock.drift()


def test_a_fast_and_a_true_clock_are_followed_too() -> None:
    for ratio in (1.0, 1.01):
        clock = BootClockOffset()
        stamps = list(_stamps(ratio, 30.0, seed=1))
        for wall, boot, _ in stamps:
            clock.observe(wall, boot)
        wall, boot, measured = stamps[-1]
        assert abs(boot + clock.offset(wall) - measured) < 0.005, ratio


def test_a_clock_that_goes_back_is_a_reboot() -> None:
    clock = BootClockOffset()
    for wall, boot, _ in _stamps(1.0, 5.0):
        clock.observe(wall, boot)
    assert clock.observe(wall + 0.02, 0.5)  # the boot clock restarted
    assert not clock.observe(wall + 0.04, 0.52)
    assert abs(clock.offset(wall + 0.04) - (wall + 0.04 - 0.52)) < 1e-9


def test_the_intakes_state_time_on_a_slow_clock() -> None:
    """Through ``TelemetryIntake``: GLOBAL_POSITION_INT stamps from a 0.990 clock; the
    state's time (what ``telemetry_age_s`` is logged from) is the measurement's."""
    now = [0.0]
    reboots = []
    intake = TelemetryIntake(
        Origin(28.6024, -81.2001, 0.0), lambda: now[0], lambda: now[0], lambda: reboots.append(1)
    )
    intake.on_attitude(SimpleNamespace(yaw=0.0, yawspeed=0.0))
    stamps = list(_stamps(0.990, 60.0, seed=2))
    for wall, boot, _ in stamps:
        now[0] = wall
        msg = SimpleNamespace(
            lat=286024000, lon=-812001000, vx=100, vy=0, hdg=0, time_boot_ms=int(boot * 1e3)
        )
        intake.on_position(msg)
    measured = stamps[-1][2]
    t = intake.build((1, 0.8, 0.3), "OFFBOARD", True, now[0], RangeIntake()).state.t
    assert not reboots
    assert math.isfinite(t) and abs(t - measured) < 0.005, t - measured
