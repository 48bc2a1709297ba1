"""Failsafes and the safety envelope of a deployed vehicle: pure logic, time injected.

Everything here decides; nothing talks to a vehicle. The runner (``bridge.runner``) feeds
each rule what it measured this tick and obeys the ``Verdict`` that ``Failsafes.decide``
returns. Rules (issue 5, item 3), by priority:

1. a person took over (the mode left GUIDED/OFFBOARD without our request): send nothing
   more, never switch back (latched); a vehicle that comes back from a lost link in
   another mode (rebooted, or switched while we could not see it) counts as taken over;
2. SIGINT/SIGTERM or a convoy-wide abort: stop, HOLD, flush the log, exit (latched);
3. autopilot link lost (telemetry silent ``telemetry_timeout_s`` or no heartbeat
   ``heartbeat_timeout_s``): command a stop while it is gone; when it returns, HOLD and
   command nothing more (latched);
4. geofence breached, the measured gap to the predecessor below ``min_gap_m`` (centre to
   centre), or the braking-aware gap rule (``core.safety.BrakingGap``: the gap between
   bumpers less the distance needed to shed the closing speed at the braking limit below
   the margin): emergency stop and HOLD (latched);
5. an exception in the policy: stop (latched; the loop keeps running and logging);
6. a staleness stop: the member's ladder commands a stop, or the messages the vehicle needs
   (every predecessor its topology keeps) are older than ``max_msg_age_s`` (a bridge
   backstop for policies running without the ladder): stop and HOLD (latched);
7. a tick that started more than ``LATE_TICK_PERIODS`` periods late (the loop stalled):
   that tick stops;
8. the speed cap, always.

"Stop" means speed 0 with the yaw at the current heading, never a zero velocity vector
(AUTOPILOTS.md). A latched stop still sends stop setpoints, so ArduPilot's GUIDED and PX4's
OFFBOARD keep a live stream until the HOLD is confirmed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from openconvoy.core.safety import BrakingGap, bumper_gap

LATE_TICK_PERIODS = 2.0
"""A tick that starts more than this many periods late is a failsafe event: the vehicle
drove on its last setpoint unsupervised meanwhile, so that tick commands a stop."""

DRIVE, STOP, SILENT = "drive", "stop", "silent"
"""What the runner sends this tick: the (capped) policy setpoint, a stop setpoint, nothing."""


@dataclass(frozen=True)
class Verdict:
    """The failsafes' decision for one tick.

    Attributes:
        command: ``DRIVE``, ``STOP`` or ``SILENT``.
        hold: ask the autopilot for its hold mode now.
        exit: end the run after this tick (log flushed, HOLD confirmed).
        failsafe: a bridge failsafe holds the vehicle (log mode ``failsafe``).
        reason: why, for the log and the status line ("" when driving normally).
    """

    command: str = DRIVE
    hold: bool = False
    exit: bool = False
    failsafe: bool = False
    reason: str = ""


class LinkWatchdog:
    """Autopilot link health from the times telemetry and heartbeats last arrived.

    ``update`` returns ``"ok"``, ``"lost"`` (silent now) or ``"returned"`` (fresh again
    after a loss; reported on every tick from then on, since the run is held). Times are
    seconds on one monotonic clock.
    """

    def __init__(self, telemetry_timeout_s: float = 0.5, heartbeat_timeout_s: float = 3.0) -> None:
        self.telemetry_timeout_s = telemetry_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.was_lost = False
        self.t_lost: float | None = None
        """Clock time the loss was first detected (s), None if never."""

    def fresh(self, now: float, t_telemetry: float, t_heartbeat: float, open_: bool = True) -> bool:
        return (
            open_
            and now - t_telemetry <= self.telemetry_timeout_s
            and now - t_heartbeat <= self.heartbeat_timeout_s
        )

    def update(self, now: float, t_telemetry: float, t_heartbeat: float, open_: bool = True) -> str:
        if not self.fresh(now, t_telemetry, t_heartbeat, open_):
            if not self.was_lost:
                self.t_lost = now
            self.was_lost = True
            return "lost"
        return "returned" if self.was_lost else "ok"


@dataclass(frozen=True)
class Envelope:
    """Limits that hold whatever the policy says.

    Attributes:
        speed_cap_mps: commanded speed never exceeds this (m/s).
        geofence_radius_m: distance from the convoy origin (m, ENU) beyond which the vehicle
            is stopped; also when the commanded speed would carry it out within
            ``geofence_lookahead_s``.
        geofence_lookahead_s: prediction horizon of the geofence (s).
        min_gap_m: emergency stop when the measured gap to the predecessor (centre to
            centre, m) falls below this.
        max_msg_age_s: stop while the messages the vehicle needs are older than this (s);
            inf disables.
        braking: the braking-aware gap rule (None: centre-to-centre ``min_gap_m`` only).
        ego_length_m, pred_length_m: the vehicle's and its predecessor's lengths (m), for
            the gap between bumpers.
    """

    speed_cap_mps: float = 5.0
    geofence_radius_m: float = 200.0
    geofence_lookahead_s: float = 1.0
    min_gap_m: float = 1.0
    max_msg_age_s: float = 3.0
    braking: BrakingGap | None = None
    ego_length_m: float = 0.0
    pred_length_m: float = 0.0

    def cap(self, speed_mps: float) -> float:
        """The commanded speed clipped to [0, cap] (NaN becomes 0)."""
        if not math.isfinite(speed_mps):
            return 0.0
        return min(max(speed_mps, 0.0), self.speed_cap_mps)

    def outside_fence(self, x: float, y: float, heading: float, speed_cmd: float) -> bool:
        """True when (x, y), or where the command leads within the lookahead, is outside."""
        r = self.geofence_radius_m
        if math.hypot(x, y) > r:
            return True
        d = max(speed_cmd, 0.0) * self.geofence_lookahead_s
        return math.hypot(x + d * math.cos(heading), y + d * math.sin(heading)) > r

    def too_close(self, gap_m: float, closing_mps: float = 0.0) -> str:
        """Why the gap (m, centre to centre; closing speed m/s, positive = closing) calls
        for an emergency stop, "" when it does not (or is unknown)."""
        if not math.isfinite(gap_m):
            return ""
        if gap_m < self.min_gap_m:
            return f"gap {gap_m:.2f} m below minimum"
        if self.braking is not None:
            bumpers = bumper_gap(gap_m, self.ego_length_m, self.pred_length_m)
            if self.braking.too_close(bumpers, closing_mps):
                return self.braking.reason(bumpers, closing_mps)
        return ""


@dataclass
class TickInputs:
    """What the runner measured this tick (all optional except ``now``).

    Attributes:
        now: monotonic clock, s.
        t_telemetry, t_heartbeat: when the newest telemetry / heartbeat arrived, s.
        link_open: the connection exists (TCP/serial not lost).
        pilot_took_over: the link saw a mode change we did not ask for.
        stop_requested: a signal asked to stop ("" = none; else its name).
        abort: a convoy-wide abort was received.
        x, y, heading: own ENU position (m) and heading (rad).
        speed_cmd: the speed the policy asks for (m/s).
        gap_m: measured gap to the predecessor (m), NaN when unknown / leader.
        closing_mps: how fast that gap shrinks (m/s, positive = closing).
        needed_age_s: age of the oldest message the vehicle needs (s), 0 for the leader.
        stale_stop: the member's staleness ladder commands a stop.
        policy_error: the policy raised this tick (its message), "" if not.
        held: the autopilot reports its hold mode.
        late_periods: how late this tick started, in loop periods (0 = on time).
        ending: the run is over for this reason (duration reached) and brakes to rest:
            stop, no failsafe ("" = driving on).
    """

    now: float
    t_telemetry: float = -math.inf
    t_heartbeat: float = -math.inf
    link_open: bool = True
    pilot_took_over: bool = False
    stop_requested: str = ""
    abort: bool = False
    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    speed_cmd: float = 0.0
    gap_m: float = math.nan
    closing_mps: float = 0.0
    needed_age_s: float = 0.0
    stale_stop: bool = False
    policy_error: str = ""
    held: bool = False
    late_periods: float = 0.0
    ending: str = ""


@dataclass
class Failsafes:
    """All rules together; ``decide`` once per tick. Latched states persist for the run."""

    envelope: Envelope = field(default_factory=Envelope)
    watchdog: LinkWatchdog = field(default_factory=LinkWatchdog)
    latched: str = ""
    """Reason of a latched stop ("" when none)."""
    latched_hold: bool = False
    took_over: bool = False
    exiting: str = ""
    policy_errors: int = 0
    events: list[tuple[float, str]] = field(default_factory=list)
    """(clock s, reason) each time a rule first fired."""
    _was_late: bool = False

    def _fire(self, now: float, reason: str) -> None:
        self.events.append((now, reason))

    def decide(self, inp: TickInputs) -> Verdict:
        now = inp.now
        if inp.pilot_took_over or self.took_over:
            if not self.took_over:
                # Event first, flag second: a thread that sees the flag also sees the event.
                self._fire(now, "pilot took over")
                self.took_over = True
            # A signal or an abort still ends the run (log saved), commanding nothing.
            leaving = bool(inp.stop_requested or inp.abort)
            return Verdict(SILENT, exit=leaving, failsafe=True, reason="pilot took over")
        if inp.stop_requested or inp.abort or self.exiting:
            if not self.exiting:
                self.exiting = inp.stop_requested or "convoy abort"
                self._fire(now, self.exiting)
            return Verdict(STOP, hold=True, exit=True, failsafe=True, reason=self.exiting)
        if inp.ending:  # a completed run braking to rest: no rule can fire any more
            return Verdict(STOP, hold=True, exit=True, reason=inp.ending)
        link = self.watchdog.update(now, inp.t_telemetry, inp.t_heartbeat, inp.link_open)
        if link == "lost":
            if self.watchdog.t_lost == now:
                self._fire(now, "autopilot link lost")
            return Verdict(STOP, failsafe=True, reason="autopilot link lost")
        if link == "returned" and not self.latched:
            self._latch(now, "autopilot link returned after a loss", hold=True)
        if not self.latched:
            if self.envelope.outside_fence(inp.x, inp.y, inp.heading, inp.speed_cmd):
                self._latch(now, "geofence", hold=True)
            elif why := self.envelope.too_close(inp.gap_m, inp.closing_mps):
                self._latch(now, why, hold=True)
        if inp.policy_error:
            self.policy_errors += 1
            if not self.latched:
                self._latch(now, f"policy error: {inp.policy_error}", hold=False)
        if not self.latched:
            # A stop for stale messages ends in HOLD, as the issue asks: coming back on
            # fresh messages would restart a vehicle nobody watched stop.
            if inp.stale_stop:
                self._latch(now, "staleness ladder stop", hold=True)
            elif inp.needed_age_s > self.envelope.max_msg_age_s:
                self._latch(now, "messages needed are stale", hold=True)
        if self.latched:
            # Keep streaming stop setpoints until the autopilot confirms HOLD, then go quiet.
            if self.latched_hold and inp.held:
                return Verdict(SILENT, failsafe=True, reason=self.latched)
            return Verdict(STOP, hold=self.latched_hold, failsafe=True, reason=self.latched)
        if inp.late_periods > LATE_TICK_PERIODS:
            # Each late episode is one event; the late tick itself stops the vehicle.
            if not self._was_late:
                self._fire(now, f"control loop late ({inp.late_periods:.1f} periods)")
            self._was_late = True
            return Verdict(STOP, failsafe=True, reason="control loop late")
        self._was_late = False
        return Verdict(DRIVE)

    def _latch(self, now: float, reason: str, hold: bool) -> None:
        self._fire(now, reason)
        self.latched_hold = hold
        self.latched = reason


@dataclass
class LoopTimer:
    """Fixed-rate schedule with overrun counting; clock in seconds.

    ``wait_time(now)`` says how long to sleep until the next tick. ``begin(now)`` returns
    how late the tick started (s). Every scheduled slot that passed without a tick is an
    overrun (a tick one and a half periods late missed one slot; a 3.7 s stall at 20 Hz
    missed 74), and the schedule skips the missed slots instead of bursting to catch up.
    """

    period_s: float
    start: float
    overruns: int = 0
    """Scheduled slots that passed without a tick."""
    ticks: int = 0
    late_ticks: int = 0
    """Ticks that started more than ``LATE_TICK_PERIODS`` periods late."""
    max_late_s: float = 0.0
    _next: float = field(init=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"loop period must be positive and finite, got {self.period_s}")
        self._next = self.start

    @property
    def next_tick(self) -> float:
        return self._next

    def begin(self, now: float) -> float:
        """Mark a tick started at ``now``; advance the schedule. Returns the lateness (s)."""
        self.ticks += 1
        late = max(now - self._next, 0.0)
        missed = math.floor(late / self.period_s)
        if missed:
            self.overruns += missed
            self._next += missed * self.period_s
        if late > LATE_TICK_PERIODS * self.period_s:
            self.late_ticks += 1
        self.max_late_s = max(self.max_late_s, late)
        self._next += self.period_s
        return late

    def wait_time(self, now: float) -> float:
        return max(0.0, self._next - now)
