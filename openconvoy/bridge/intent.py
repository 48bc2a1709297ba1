"""What a vehicle's controller wants on one deploy tick, before the failsafes have a say.

A follower: ``policy.act`` on the member's observation, then the member's decision
(``core.tick.decide``: the finite check, the clip to the action space, the staleness
ladder fed with the rangefinder as in ``sim``). The leader: its scenario or track driver
(``bridge.leaderdrive``). Either, while the convoy has not started: stand still.
"""

from __future__ import annotations

import logging
import math
import time
import traceback
from collections.abc import Callable

from openconvoy.bridge.convoystart import ConvoyStart
from openconvoy.bridge.failsafes import Failsafes
from openconvoy.bridge.leaderdrive import LeaderDriving
from openconvoy.bridge.link import Telemetry
from openconvoy.core import tick as member_tick
from openconvoy.core.member import ConvoyMember, Frame
from openconvoy.core.policy import ActGuard, ConvoyPolicy, PolicyFailure
from openconvoy.core.state import VehicleState

log = logging.getLogger(__name__)

RANGE_MAX_AGE_S = 0.5
"""A rangefinder reading older than this (s) is not passed to the staleness ladder."""

Want = tuple[float, float, str, str]
"""(speed m/s, heading change rad, mode, policy error message or "")."""


def ranging_ahead(
    tel: Telemetry, lengths: list[float], vehicle_id: int, now: float
) -> tuple[float, float] | None:
    """(range, range rate) to the vehicle ahead for the staleness ladder, centre to centre
    (m, m/s) as in ``sim``: the rangefinder reads from the front bumper to the predecessor's
    rear, so half of each length is added. None for the leader or without a fresh reading
    (older than ``RANGE_MAX_AGE_S`` at monotonic ``now``)."""
    r, rate = tel.range_m, tel.range_rate_mps
    if vehicle_id == 0 or not (math.isfinite(r) and math.isfinite(rate)):
        return None
    if now - tel.t_range > RANGE_MAX_AGE_S:
        return None
    return r + 0.5 * (lengths[vehicle_id] + lengths[vehicle_id - 1]), rate


def follower_decision(
    policy: ConvoyPolicy | ActGuard,
    member: ConvoyMember,
    frame: Frame,
    bounds: member_tick.ActionBounds,
    ranging: tuple[float, float] | None,
    wall: float,
    first_error: bool,
) -> member_tick.Decision:
    """``policy.act`` on the frame's observation, then the member's decision
    (``core.tick.decide``); a policy that raises gets a stop decision naming the error (the
    traceback is logged for the ``first_error`` only). Through an ``ActGuard`` (what the
    runner passes), an ``act`` slower than the control period ``LATE_ACTS`` times in a
    row is a policy error too, as in ``sim``."""
    try:
        action = (
            policy(frame.observation)
            if isinstance(policy, ActGuard)
            else policy.act(frame.observation)
        )
    except Exception as exc:  # the policy is foreign code: stop, log, keep looping
        if first_error:
            log.error("policy raised at t=%.2f:\n%s", wall, traceback.format_exc())
        return member_tick.stop(f"{type(exc).__name__}: {exc}")
    if isinstance(action, PolicyFailure) and first_error:
        tb = policy.traceback if isinstance(policy, ActGuard) else ""
        if tb:
            log.error("policy raised at t=%.2f:\n%s", wall, tb)
        else:
            log.error("policy error at t=%.2f: %s", wall, action.reason)
    return member_tick.decide(member, frame, action, bounds, ranging)


class ControllerIntent:
    """The controller's side of a tick for one vehicle.

    Args:
        member: the convoy member (its lengths, its decision).
        bounds: the action space the policy's action is clipped to.
        leading: the leader's driver (used when this vehicle leads).
        start_gate: when the convoy started.
        failsafes: counts policy errors (the first one's traceback is logged).
        period_s: the control period (s) ``act`` must keep within (``ActGuard``).
        clock: seconds, to time ``act``.

    Attributes:
        decision: the member's latest decision (None for a leader, or while waiting).
    """

    def __init__(
        self,
        member: ConvoyMember,
        bounds: member_tick.ActionBounds,
        leading: LeaderDriving,
        start_gate: ConvoyStart,
        failsafes: Failsafes,
        period_s: float = 0.05,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.period_s, self.clock = period_s, clock
        self.guard: ActGuard | None = None
        """Times the follower's ``act`` (``guard.times``: seconds per call); the first
        ``act`` slower than half the period is a warning in the log, at once."""
        self._warned_slow = False
        self.member = member
        self.bounds = bounds
        self.leading = leading
        self.start_gate = start_gate
        self.failsafes = failsafes
        self.decision: member_tick.Decision | None = None

    def want(
        self,
        policy: ConvoyPolicy,
        tel: Telemetry,
        own: VehicleState,
        frame: Frame,
        waiting: bool,
        clocks: tuple[float, float],
    ) -> Want:
        """What ``policy`` (a follower's) or the leader's driver wants at (monotonic,
        wall) ``clocks`` (s), given the telemetry, own state and the member's frame."""
        now, wall = clocks
        if waiting:  # armed and still, yaw at the current heading
            return 0.0, 0.0, "stop", ""
        vehicle_id = self.member.vehicle_id
        if vehicle_id == 0:
            t_start = self.start_gate.t_start
            assert t_start is not None  # not waiting: started
            return self.leading.command(tel, own, now, t_start)
        if self.guard is None or self.guard.policy is not policy:
            self.guard = ActGuard(policy, self.period_s, self.clock)
            self._warned_slow = False
        self.decision = d = follower_decision(
            self.guard,
            self.member,
            frame,
            self.bounds,
            ranging_ahead(tel, self.member.lengths, vehicle_id, now),
            wall,
            first_error=not self.failsafes.policy_errors,
        )
        times = self.guard.times
        if times and times[-1] > 0.5 * self.period_s and not self._warned_slow:
            self._warned_slow = True  # once a run: the end-of-run report has the figures
            log.warning(
                "vehicle %d: policy act took %.1f ms, over half the %.0f ms control period",
                vehicle_id,
                times[-1] * 1e3,
                self.period_s * 1e3,
            )
        return d.speed_mps, d.heading_change_rad, d.mode, d.policy_error
