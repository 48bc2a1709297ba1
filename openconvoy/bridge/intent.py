"""What a vehicle's controller wants on one deploy tick, before the failsafes have a say.

The member's whole tick is ``core.tick.tick``, the simulator's rules: τ and the broadcast,
ρ on what was received, then a follower's ``policy.act`` (through an ``ActGuard``, its
first error logged) and the member's decision (``core.tick.decide``: the finite check, the
clip to the action space, the staleness ladder fed with the rangefinder as in ``sim``).
The leader: its scenario or track driver (``bridge.leaderdrive``). Either, while the
convoy has not started: stand still.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from openconvoy.bridge.convoystart import ConvoyStart
from openconvoy.bridge.failsafes import Failsafes
from openconvoy.bridge.leaderdrive import LeaderDriving
from openconvoy.bridge.link import Telemetry
from openconvoy.core import tick as member_tick
from openconvoy.core.member import ConvoyMember
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


@dataclass(frozen=True, slots=True)
class FollowerAct:
    """A follower's policy as one tick calls it (``core.tick.Actor``): ``intent``'s guarded
    ``act`` of ``policy`` at shared-clock time ``wall`` (s), for the log."""

    intent: ControllerIntent
    policy: ConvoyPolicy
    wall: float

    def act(self, observation: np.ndarray) -> np.ndarray | PolicyFailure:
        """The action for ``observation``, or the ``PolicyFailure`` that stops the vehicle."""
        return self.intent.guarded_act(self.policy, observation, self.wall)


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

    def tick(
        self,
        policy: ConvoyPolicy,
        tel: Telemetry,
        own: VehicleState,
        known: bool,
        radio: member_tick.Radio,
        clocks: tuple[float, float],
        started: Callable[[], bool],
    ) -> tuple[member_tick.TickResult, Want]:
        """The member's tick (``core.tick.tick``, as in ``sim``) at (monotonic, wall)
        ``clocks`` (s), with the own state from telemetry ``tel`` (broadcast on ``radio``
        only while it is ``known``) and ``started`` asked after sensing; then what
        ``policy`` (a follower's) or the leader's driver wants."""
        now, wall = clocks
        vehicle_id = self.member.vehicle_id
        result = member_tick.tick(
            self.member,
            None if vehicle_id == 0 else FollowerAct(self, policy, wall),
            own,
            radio,
            wall,
            self.bounds,
            ranging_ahead(tel, self.member.lengths, vehicle_id, now),
            may_send=known,
            started=started,
        )
        if not result.started:  # armed and still, yaw at the current heading
            return result, (0.0, 0.0, "stop", "")
        if vehicle_id == 0:
            t_start = self.start_gate.t_start
            assert t_start is not None  # started
            return result, self.leading.command(tel, own, now, t_start)
        assert result.decision is not None  # a started follower decides
        self.decision = d = result.decision
        self._warn_if_slow()
        return result, (d.speed_mps, d.heading_change_rad, d.mode, d.policy_error)

    def guarded_act(
        self, policy: ConvoyPolicy, observation: np.ndarray, wall: float
    ) -> np.ndarray | PolicyFailure:
        """``policy.act`` through an ``ActGuard`` (a new one when the policy changed): the
        action, or the ``PolicyFailure`` of an ``act`` that raised or overran the period
        too often; the first policy error of a run is logged (with its traceback) at
        shared-clock time ``wall`` (s)."""
        if self.guard is None or self.guard.policy is not policy:
            self.guard = ActGuard(policy, self.period_s, self.clock)
            self._warned_slow = False
        action = self.guard(observation)
        if isinstance(action, PolicyFailure) and not self.failsafes.policy_errors:
            if self.guard.traceback:
                log.error("policy raised at t=%.2f:\n%s", wall, self.guard.traceback)
            else:
                log.error("policy error at t=%.2f: %s", wall, action.reason)
        return action

    def _warn_if_slow(self) -> None:
        """The first ``act`` slower than half the period is a warning, once a run (the
        end-of-run report has the figures)."""
        times = self.guard.times if self.guard is not None else []
        if times and times[-1] > 0.5 * self.period_s and not self._warned_slow:
            self._warned_slow = True
            log.warning(
                "vehicle %d: policy act took %.1f ms, over half the %.0f ms control period",
                self.member.vehicle_id,
                times[-1] * 1e3,
                self.period_s * 1e3,
            )
