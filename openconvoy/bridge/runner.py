"""The real-time runner behind ``openconvoy deploy``: the simulator's tick, on a vehicle.

Each tick, at a fixed rate (20 Hz by default; clock and sleep injected):

1. read telemetry (``VehicleLink.poll``) and give it to the convoy member (``observe_own``);
2. τ: broadcast the own state when the Tx gate says so (``v2v.send``);
3. drain received messages (the loss model is applied inside ``v2v``) through ρ
   (``member.receive``); an abort message ends the run;
4. build the observation, ``policy.act`` (the same policy object type as in simulation —
   nothing here or there asks which world it runs in), ``member.supervise`` (the staleness
   ladder); the leader instead follows its scenario or track (speed profile and the same
   heading controller as the simulated leader), or commands nothing when ``passive``;
5. the failsafes and safety envelope (``bridge.failsafes``) decide what is sent;
6. send the setpoint: speed and absolute yaw = current heading + heading change;
7. write the log row (``openconvoy.logs``, the simulator's columns).

Followers wait, armed and still (speed 0, yaw = current heading), until they hear the leader
and the predecessors their topology keeps; a scenario-driven leader waits until it has heard
every member, so the convoy starts moving together as it does in simulation. When its
scenario is over the leader brakes to rest, still broadcasting (its followers see it stop
and stop behind it), then holds and ends.
"""

from __future__ import annotations

import logging
import math
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from openconvoy.bridge.failsafes import (
    DRIVE,
    STOP,
    Envelope,
    Failsafes,
    LinkWatchdog,
    LoopTimer,
    TickInputs,
    Verdict,
)
from openconvoy.bridge.link import LinkTimeout, Telemetry, VehicleLink, VehicleLinkError
from openconvoy.bridge.recorder import RunRecorder
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.convoy import ConvoyConfig
from openconvoy.core import tick as member_tick
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import ConvoyMember, Frame, member_config_for
from openconvoy.core.policy import ConvoyPolicy, as_convoy_policy
from openconvoy.core.spacing import SpacingConfig
from openconvoy.core.state import VehicleState, wrap_angle

log = logging.getLogger(__name__)

EXTRA_COLUMNS = ("length_m", "msgs_kept", "loop_overruns", "telemetry_age_s")
"""Numeric log columns after DESIGN.md's: the vehicle's length (as ``sim`` writes, so
``report`` counts collisions from the log alone), the messages the Rx gate kept, the loop
overruns so far, and how old the telemetry behind the row was (s; ``fit-plant`` removes it
from the fitted actuation delay). As in ``sim``, ``msgs_received``/``msgs_lost`` count what the link
delivered / the loss model dropped, before the Rx gate. Why a failsafe fired goes to the
metadata JSON (``failsafe_events``)."""

HOLD_MODES = ("HOLD", "LOITER")
RECEIVE_BUDGET = 0.4
"""Share of a loop period the V2V receive may take per tick; datagrams beyond it wait for
the next tick (a flood of them costs messages, never the loop's timing)."""
FINISH_TIMEOUT_S = 10.0
"""Longest a leader brakes after its scenario before ending the run anyway (s)."""
HOLD_BELOW_MPS = 0.1
"""HOLD is requested once the vehicle is this slow (m/s) under stop setpoints, or after
``_brake_time_s``: PX4's Hold loops back to where it engaged (150 °/s turns from 2 m/s,
shared/sitl-px4 row 23) and ArduPilot's coasts without braking (4.4 s from 2 m/s against
1.9 s for a stop setpoint, shared/sitl rows 20, 23)."""
RANGE_MAX_AGE_S = 0.5
"""A rangefinder reading older than this (s) is not passed to the staleness ladder."""


class V2VEndpoint(Protocol):
    """What the runner needs from V2V (``comms.v2v.V2V``, or ``bridge.localv2v.LocalV2V``):
    ``counters`` with ``sent``, ``received``, ``lost``; ``metadata`` (a dict property)."""

    counters: Any

    def send(self, state: VehicleState, now: float) -> bool: ...

    def poll(self, now: float, budget_s: float | None = None) -> list[Any]:
        """Messages heard since the last poll: objects with ``state`` (VehicleState with
        ``vehicle_id`` = convoy index, ``t`` = sender time), ``t_rx`` and ``abort``; reading
        for at most ``budget_s`` seconds when given."""
        ...

    @property
    def metadata(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class LeaderDriver(Protocol):
    """The leader's driver (``envs.scenarios.Scenario`` has this method)."""

    duration_s: float

    def leader_command(self, t: float, x: float, y: float, heading: float, speed: float) -> tuple[float, float]: ...


class StopRequested(Exception):
    """A signal asked to stop before the loop was running (while connecting or arming)."""


@dataclass(frozen=True)
class RunnerOptions:
    """How one vehicle runs.

    Attributes:
        vehicle_id: convoy index, 0 = leader.
        rate_hz: control loop rate, Hz.
        dry_run: everything but arming and sending setpoints.
        passive: leader only: a person drives; broadcast and log, command nothing.
        duration_s: end the run this long after the convoy started moving (s); None = the
            leader's scenario duration for a scenario-driven leader, else until stopped.
        connect_timeout_s: wait this long for the autopilot's heartbeat and telemetry (s).
        arm_timeout_s: wait this long for arming to become possible (s).
        leader_waits_for_convoy: a scenario-driven leader starts only once it heard every
            member (or after ``convoy_wait_s``).
        convoy_wait_s: the longest such wait (s).
        status_period_s: status line period (s); 0 = none.
        record_timing: keep per-tick timings (benchmarks).
        seed: seeds the leader scenario's randomness.
    """

    vehicle_id: int
    rate_hz: float = 20.0
    dry_run: bool = False
    passive: bool = False
    duration_s: float | None = None
    connect_timeout_s: float = 30.0
    arm_timeout_s: float = 60.0
    leader_waits_for_convoy: bool = True
    convoy_wait_s: float = 120.0
    status_period_s: float = 1.0
    record_timing: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        # Checked here too (the CLI checks its flags): a NaN rate or timeout would busy-loop
        # setpoints to the autopilot or wait forever.
        for what, value, hi in (
            ("control rate (--rate, or the policy's control_rate_hz), Hz", self.rate_hz, 100.0),
            ("--connect-timeout, s", self.connect_timeout_s, 86400.0),
            ("--arm-timeout, s", self.arm_timeout_s, 86400.0),
            ("--duration, s", 1.0 if self.duration_s is None else self.duration_s, 7 * 86400.0),
        ):
            if not (math.isfinite(value) and 0.0 < value <= hi):
                raise ConfigError(f"{what}: {value!r} is out of range; allowed: a finite number in (0, {hi:g}]")
        if self.passive and self.vehicle_id != 0:
            raise ConfigError("--passive is for the leader (vehicle 0): followers are driven by the policy")


@dataclass
class RunResult:
    """How a run ended."""

    exit_code: int
    reason: str
    ticks: int
    overruns: int
    policy_errors: int
    t_start_s: float | None
    events: list[tuple[float, str]] = field(default_factory=list)


@dataclass
class TickTiming:
    """Monotonic times (s) of one tick: start, telemetry read, setpoint sent (NaN if none),
    and when the newest telemetry used had been read (``Telemetry.t_telemetry``)."""

    t_tick: float
    t_polled: float
    t_sent: float
    t_telemetry: float


def scenario_spacing(convoy: ConvoyConfig) -> SpacingConfig:
    """The convoy scenario's spacing σ: what the simulator gives a policy without a member
    config of its own (``member.member_config_for``)."""
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.envs.vehicles import vehicle_preset

    return make_scenario(convoy.scenario, presets=[vehicle_preset(v) for v in convoy.vehicles]).spacing


def top_speed(convoy: ConvoyConfig, vehicle_id: int) -> float:
    """The vehicle's preset top speed (m/s): the top of its action space, as in ``sim``."""
    from openconvoy.envs.vehicles import vehicle_preset

    return vehicle_preset(convoy.vehicles[vehicle_id]).max_speed_mps


def envelope_from(convoy: ConvoyConfig, vehicle_id: int | None = None) -> Envelope:
    """The safety envelope a convoy config asks for; with ``vehicle_id``, the braking-aware
    gap rule from that vehicle's preset (margin ``[safety] gap_margin_m`` or its default)."""
    s = convoy.safety
    braking, ego_len, pred_len = None, 0.0, 0.0
    if vehicle_id is not None and vehicle_id > 0:
        from openconvoy.core.safety import for_vehicle
        from openconvoy.envs.vehicles import vehicle_preset

        ego, pred = vehicle_preset(convoy.vehicles[vehicle_id]), vehicle_preset(convoy.vehicles[vehicle_id - 1])
        braking = for_vehicle(ego.decel_max_mps2, ego.actuation_delay_s, ego.speed_lag_s, ego.length_m,
                              s.gap_margin_m)
        ego_len, pred_len = ego.length_m, pred.length_m
    return Envelope(
        speed_cap_mps=s.speed_cap_mps,
        geofence_radius_m=s.geofence_radius_m,
        min_gap_m=s.min_gap_m,
        max_msg_age_s=s.max_msg_age_s,
        braking=braking, ego_length_m=ego_len, pred_length_m=pred_len,
    )


class DeployRunner:
    """One vehicle's real-time loop. ``run()`` connects, arms, loops and returns a
    ``RunResult``; ``request_stop(name)`` (signal handlers) ends it cleanly.

    Args:
        options: see ``RunnerOptions``.
        convoy: the convoy (size, origin, safety).
        policy: any ``core.policy.Policy`` (``policies.load_policy``); its ``member_config``
            configures the member.
        link: the vehicle (``VehicleLink``).
        v2v: the V2V endpoint (``V2VEndpoint``).
        leader: the leader's driver (a scenario), required for a non-passive leader.
        lengths: vehicle lengths (m), leader first, for the member's desired gaps.
        decels: vehicle braking limits (m/s²), leader first: how far a silent predecessor
            can have got (None: it is taken to have stopped where last heard).
        log_dir: directory for ``vehicle_N.csv`` and ``vehicle_N.json``; None = no log.
        clock: monotonic clock (s) for the schedule and failsafes.
        sleep: sleeps that many seconds.
        wall_clock: the shared (GPS/NTP) clock (s) stamped in logs and messages.
        on_status: receives status lines.
        leader_origin: the geodetic origin of the leader driver's frame when it differs
            from the convoy's (track files carry their own); None = the convoy's.
        metadata: extra entries for the run metadata JSON.
        bounds: the action space the policy's action is clipped to (default: speed up to
            this vehicle's preset top speed, as in ``sim``).
        spacing: σ for a policy without a member config (default: the convoy
            scenario's, as in ``sim``).
    """

    def __init__(
        self,
        options: RunnerOptions,
        convoy: ConvoyConfig,
        policy: ConvoyPolicy,
        link: VehicleLink,
        v2v: V2VEndpoint,
        *,
        leader: LeaderDriver | None = None,
        lengths: list[float] | None = None,
        decels: list[float] | None = None,
        log_dir: str | Path | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        wall_clock: Callable[[], float] = time.time,
        on_status: Callable[[str], None] | None = None,
        leader_origin: Origin | None = None,
        envelope: Envelope | None = None,
        metadata: dict[str, Any] | None = None,
        bounds: member_tick.ActionBounds | None = None,
        spacing: SpacingConfig | None = None,
    ) -> None:
        n = convoy.n_vehicles
        if not 0 <= options.vehicle_id < n:
            raise ConfigError(f"vehicle id {options.vehicle_id} not in this convoy of {n} vehicles (0..{n - 1})")
        self.is_leader = options.vehicle_id == 0
        if self.is_leader and not options.passive and leader is None:
            raise ConfigError("the leader needs a scenario or track to follow, or --passive")
        self.options = options
        self.convoy = convoy
        self.link = link
        self.v2v = v2v
        self.leader = leader
        self.clock = clock
        self.sleep = sleep
        self.wall = wall_clock
        self.on_status = on_status or (lambda line: log.warning("%s", line))
        self.origin = Origin(*convoy.origin)
        self.leader_origin = leader_origin
        self.policy = as_convoy_policy(policy)
        self.member = self._member(spacing, lengths, decels)
        self.bounds = bounds or member_tick.ActionBounds.float32(top_speed(convoy, options.vehicle_id))
        self.frame: Frame = Frame(math.nan, self.member.layout.zeros())
        """The member's latest frame (its observation and derived values)."""
        self.decision: member_tick.Decision | None = None
        """The member's latest decision (None for a leader, or while waiting to start)."""
        self.failsafes = Failsafes(
            envelope=envelope or envelope_from(convoy, options.vehicle_id),
            watchdog=LinkWatchdog(link.telemetry_timeout_s, link.heartbeat_timeout_s),
        )
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.metadata_extra = dict(metadata or {})
        self.timings: list[TickTiming] = []
        self._init_run_state()

    def _member(self, spacing: SpacingConfig | None, lengths: list[float] | None,
                decels: list[float] | None) -> ConvoyMember:
        """The convoy member, configured as in ``sim``: the policy's member config, or for
        a policy without one the convoy scenario's spacing (``member_config_for``)."""
        config = self.policy.member_config
        if config is None and spacing is None:
            spacing = scenario_spacing(self.convoy)
        member_config = member_config_for(config, spacing or SpacingConfig())
        return ConvoyMember(self.options.vehicle_id, self.convoy.n_vehicles, member_config, lengths, decels)

    def _init_run_state(self) -> None:
        """What one run accumulates (stop requests, start and end times, timers, HOLD and
        broadcast bookkeeping)."""
        self._stop_requested = ""
        self._abort = False
        self._tel: Telemetry | None = None
        self._t_start: float | None = None  # monotonic time the convoy started moving
        self._t_start_wall: float | None = None
        self._t_finish: float | None = None  # monotonic time a leader's scenario ended
        self._heard_raw: set[int] = set()
        self.recorder = RunRecorder(self.log_dir, self.options.vehicle_id, EXTRA_COLUMNS)
        self._timer: LoopTimer | None = None
        self._late_periods = 0.0
        self._t_hold_sent = -math.inf
        self._t_status = -math.inf
        self._t_reconnect = -math.inf
        self._last_reason = ""
        self._armed_by_us = False
        self._arming = False  # prepare_and_arm was entered and did not return
        self._t_stop = math.nan  # when the current stop-and-hold began (monotonic s)
        self._v_stop = 0.0  # speed then (m/s)
        self._broadcasting = True
        self._broadcast_pauses: list[list[float | None]] = []  # [wall from, wall to]
        self._t_begin_wall = self.wall()

    # ------------------------------------------------------------------ control

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the loop to stop, HOLD, flush the log and return (safe from signal handlers)."""
        self._stop_requested = reason

    @property
    def commanding(self) -> bool:
        """Whether this run sends setpoints at all (not dry-run, not passive)."""
        return not (self.options.dry_run or self.options.passive)

    # ------------------------------------------------------------------ run

    def start(self) -> None:
        """Connect, wait for telemetry, arm (unless dry-run/passive), open the log."""
        o = self.options
        deadline = self.clock() + o.connect_timeout_s
        while True:  # short attempts, so that a signal is obeyed while waiting
            self._check_stop()
            try:
                self.link.connect(min(1.0, max(0.05, deadline - self.clock())))
                break
            except LinkTimeout as exc:
                if self.clock() >= deadline:  # the attempt's own timeout is not the user's
                    why = str(exc).split(" within ")[0]
                    raise LinkTimeout(f"{why} within --connect-timeout {o.connect_timeout_s:g} s") from None
        while self._tel is None:
            self._check_stop()
            self._tel = self.link.poll()
            if self._tel is None:
                if self.clock() > deadline:
                    raise TimeoutError(f"no position telemetry from the vehicle within {o.connect_timeout_s:g} s")
                self.sleep(0.01)
        if self.commanding and not self._stop_requested:
            self.on_status(f"vehicle {o.vehicle_id}: arming ({self.link.autopilot})")
            # Arming may wait ~40 s for the estimator: status lines come every retry, and
            # a signal meanwhile ends the run through ``_status_or_stop``.
            self._arming = True
            self.link.prepare_and_arm(o.arm_timeout_s, self._status_or_stop)
            self._armed_by_us, self._arming = True, False
            # Stand still with the yaw at the current heading from the first moment.
            self.link.stop_motion()
        self.recorder.open()
        self.policy.reset(o.seed)
        if self.leader is not None and hasattr(self.leader, "reset"):
            self.leader.reset(np.random.default_rng(o.seed))
        self.on_status(
            f"vehicle {o.vehicle_id}: ready"
            + (" (dry run: no setpoints)" if o.dry_run else "")
            + (" (passive: broadcasting only)" if o.passive else "")
        )

    def run(self) -> RunResult:
        """Start, loop until the run ends, stop safely. Never leaves the vehicle moving."""
        reason = "ended"
        code = 0
        try:
            self.start()
            period = 1.0 / self.options.rate_hz
            self._timer = timer = LoopTimer(period, self.clock())
            while True:
                wait = timer.wait_time(self.clock())
                if wait > 0:
                    self.sleep(wait)
                t_tick = self.clock()
                self._late_periods = timer.begin(t_tick) / period
                done = self.tick(t_tick)
                if done:
                    reason = done
                    break
        except StopRequested as exc:
            reason = str(exc)
        except KeyboardInterrupt:
            reason = "SIGINT"
        except (VehicleLinkError, TimeoutError) as exc:  # the vehicle said no, or nothing
            reason = f"error: {exc}"
            code = 1
            log.error("vehicle %d: %s", self.options.vehicle_id, exc)
        except Exception as exc:  # a runner bug must not leave the vehicle moving
            reason = f"error: {exc}"
            code = 1
            log.error("deploy loop failed:\n%s", traceback.format_exc())
        finally:
            code = code or self._failure_code(reason)
            self._finish(reason, code)
        return RunResult(
            exit_code=code,
            reason=reason,
            ticks=self._timer.ticks if self._timer else 0,
            overruns=self._timer.overruns if self._timer else 0,
            policy_errors=self.failsafes.policy_errors,
            t_start_s=self._t_start_wall,
            events=list(self.failsafes.events),
        )

    def _failure_code(self, reason: str) -> int:
        """1 when the run ended by a failsafe, a lost autopilot link, a takeover before the
        convoy drove or an autopilot failsafe; 0 when it completed or a person stopped it
        (signal, ``abort``) with nothing of that kind on the way."""
        f = self.failsafes
        if f.latched or f.watchdog.was_lost:
            return 1
        if f.took_over and (self._t_start is None or self.link.failsafe_took_over):
            return 1
        return 0

    def _check_stop(self) -> None:
        if self._stop_requested:
            raise StopRequested(self._stop_requested)

    def _status_or_stop(self, line: str) -> None:
        self.on_status(line)
        self._check_stop()

    # ------------------------------------------------------------------ one tick

    def tick(self, now: float) -> str:
        """One control tick at monotonic time ``now``. Returns "" to go on, else why the run ends."""
        tel, t_polled = self._read_telemetry(now)
        wall = self.wall()
        own = replace(tel.state, vehicle_id=self.options.vehicle_id)
        self.frame = frame = self._exchange(now, wall, tel, own)
        waiting = bool(self._waiting_for())
        if not waiting and self._t_start is None:
            self._t_start, self._t_start_wall = now, wall
            self.on_status(f"vehicle {self.options.vehicle_id}: convoy complete, starting")
        # What the controller wants (the member's decision, or the leader's driver) ...
        speed, change, mode, policy_error = self._intent(
            tel, own, frame, waiting, now, wall, self._ranging(tel, now))
        gap, closing = self._gap(wall)
        heading_cmd = wrap_angle(own.heading + change)
        # ... and what the failsafes and the envelope let through.
        verdict = self._verdict(now, wall, tel, own, waiting, heading_cmd, speed, gap, closing, policy_error)
        if verdict.command == DRIVE:
            speed = self.failsafes.envelope.cap(speed)
        else:
            speed, heading_cmd = 0.0, own.heading
            mode = "failsafe" if verdict.failsafe else "stop"
        t_sent = self._actuate(now, tel, own, verdict, speed, heading_cmd)
        if self.options.record_timing:
            self.timings.append(TickTiming(now, t_polled, t_sent, tel.t_telemetry))
        self._log_row(wall, own, tel, speed, wrap_angle(heading_cmd - own.heading), mode, gap,
                      sent=self.commanding and not math.isnan(t_sent))  # what really went out
        self._status_line(now, own, mode, gap)
        return verdict.reason if verdict.exit else self._end_reason(now, own)

    # ------------------------------------------------------------------ tick phases

    def _read_telemetry(self, now: float) -> tuple[Telemetry, float]:
        """The newest telemetry (the last one when none arrived) and when it was read;
        reopens a lost link now and then."""
        tel = self.link.poll()
        if tel is not None:
            self._tel = tel
        assert self._tel is not None
        t_polled = self.clock()
        self._maybe_reconnect(now)
        return self._tel, t_polled

    def _exchange(self, now: float, wall: float, tel: Telemetry, own: VehicleState) -> Frame:
        """τ and ρ (``core.tick``): broadcast the own state — only while the autopilot link
        is fresh (without it the vehicle no longer knows its own state, and a stale one with
        new timestamps would mislead the convoy) — then receive, bounded in time so that a
        flood cannot stall the loop, and sense. An abort message ends the run."""
        known = self.failsafes.watchdog.fresh(now, tel.t_telemetry, tel.t_heartbeat, not self.link.lost)
        self._track_broadcast(known, wall)
        sent = member_tick.begin(self.member, own, wall, may_send=known)
        if sent is not None:
            self.v2v.send(sent, wall)
        inbox = []
        for msg in self.v2v.poll(wall, budget_s=RECEIVE_BUDGET / self.options.rate_hz):
            if msg.abort:
                self._abort = True
            elif msg.state is not None:
                self._heard_raw.add(msg.state.vehicle_id)
                inbox.append(msg.state)
        return member_tick.sense(self.member, inbox, wall)

    def _verdict(self, now: float, wall: float, tel: Telemetry, own: VehicleState, waiting: bool,
                 heading_cmd: float, speed: float, gap: float, closing: float, policy_error: str) -> Verdict:
        """The failsafes' and the envelope's decision this tick (status line on a change)."""
        following = not self.is_leader and not waiting
        verdict = self.failsafes.decide(
            TickInputs(
                now=now, t_telemetry=tel.t_telemetry, t_heartbeat=tel.t_heartbeat,
                link_open=not self.link.lost,
                pilot_took_over=self.commanding and self.link.pilot_took_over,
                stop_requested=self._stop_requested, abort=self._abort,
                x=own.x, y=own.y, heading=heading_cmd, speed_cmd=speed if not waiting else 0.0,
                gap_m=gap, closing_mps=closing, needed_age_s=self.member.needed_age(wall) if following else 0.0,
                policy_error=policy_error, stale_stop=following and self.member.mode == "stop",
                held=tel.mode in HOLD_MODES, late_periods=self._late_periods,
            )
        )
        if verdict.reason and verdict.reason != self._last_reason:
            why = self.link.takeover_reason if verdict.reason == "pilot took over" else ""
            self.on_status(f"vehicle {self.options.vehicle_id}: {verdict.reason}" + (f" ({why})" if why else ""))
        self._last_reason = verdict.reason
        return verdict

    def _actuate(self, now: float, tel: Telemetry, own: VehicleState, verdict: Verdict,
                 speed: float, heading_cmd: float) -> float:
        """Send the setpoint (and HOLD once braked, or after the braking time); the link
        clock time it went out, NaN if none did."""
        t_sent = math.nan
        if not self.commanding:
            return t_sent
        if verdict.command in (DRIVE, STOP) and self.link.send_setpoint(speed, heading_cmd):
            t_sent = self.clock()
        if not verdict.hold:
            self._t_stop = math.nan
        elif math.isnan(self._t_stop):
            self._t_stop, self._v_stop = now, abs(own.speed)
        if (verdict.hold and now - self._t_hold_sent >= 1.0 and tel.mode not in HOLD_MODES
                and (abs(own.speed) < HOLD_BELOW_MPS
                     or now - self._t_stop >= self._brake_time_s(self._v_stop))):
            self._t_hold_sent = now
            try:
                self.link.hold(0.0)
            except Exception as exc:  # noqa: BLE001 - a hold that cannot be sent is retried
                log.warning("HOLD not sent: %s", exc)
        return t_sent

    def _end_reason(self, now: float, own: VehicleState) -> str:
        """Why the run ends after this tick ("" = it goes on): a takeover before the convoy
        drove, or the duration (a scenario-driven leader first brakes to rest)."""
        if self.failsafes.took_over and self._t_start is None and self.commanding:
            why = self.link.takeover_reason or "a mode change we did not ask for"
            return f"pilot took over before the convoy drove: {why}"
        if self._t_start is None:
            return ""
        limit = self._duration()
        # Half a period of slack: tick times are sums of floats.
        if limit is None or now - self._t_start < limit - 0.5 / self.options.rate_hz:
            return ""
        if not self._brakes_at_end():
            return "duration reached"
        if self._t_finish is None:
            self._t_finish = now
        elif abs(own.speed) < 0.05 or now - self._t_finish > FINISH_TIMEOUT_S:
            return "duration reached"
        return ""

    def _brakes_at_end(self) -> bool:
        """A scenario-driven leader brakes to rest before ending; others end at once."""
        return self.is_leader and self.commanding and self.leader is not None

    # ------------------------------------------------------------------ helpers

    def _intent(self, tel: Telemetry, own: VehicleState, frame: Frame, waiting: bool,
                now: float, wall: float, ranging: tuple[float, float] | None = None,
                ) -> tuple[float, float, str, str]:
        """What the controller wants before the failsafes: (speed m/s, heading change rad,
        mode, policy error message or "")."""
        if waiting:  # armed and still, yaw at the current heading
            return 0.0, 0.0, "stop", ""
        if self.is_leader:
            if self._t_finish is not None:
                # Scenario over: brake to rest while still broadcasting, so the followers
                # see their leader stop and stop behind it.
                return 0.0, 0.0, "stop", ""
            return self._leader_command(tel, own, now)
        try:
            action = self.policy.act(frame.observation)
        except Exception as exc:  # the policy is foreign code: stop, log, keep looping
            if not self.failsafes.policy_errors:
                log.error("policy raised at t=%.2f:\n%s", wall, traceback.format_exc())
            self.decision = member_tick.stop(f"{type(exc).__name__}: {exc}")
        else:
            self.decision = member_tick.decide(self.member, frame, action, self.bounds, ranging)
        d = self.decision
        return d.speed_mps, d.heading_change_rad, d.mode, d.policy_error

    def _duration(self) -> float | None:
        if self.options.duration_s is not None:
            return self.options.duration_s
        if self.is_leader and self.leader is not None and not self.options.passive:
            return float(self.leader.duration_s)
        return None

    def _waiting_for(self) -> list[int]:
        """Vehicles still unheard before this one may start (empty = go)."""
        if self._t_start is not None:
            return []
        i, n = self.options.vehicle_id, self.convoy.n_vehicles
        if i == 0:
            if self.options.passive or not self.options.leader_waits_for_convoy:
                return []
            if self.clock() - (self._timer.start if self._timer else self.clock()) > self.options.convoy_wait_s:
                return []
            return [j for j in range(1, n) if j not in self._heard_raw]
        need = {j for j in range(i) if self.member.rx.keeps(j)}
        need.add(0)
        return sorted(j for j in need if j not in self._heard_raw)

    def _leader_command(self, tel: Telemetry, own: VehicleState, now: float) -> tuple[float, float, str, str]:
        if self.options.passive or self.leader is None:
            return 0.0, 0.0, "coop", ""
        assert self._t_start is not None
        x, y = own.x, own.y
        if self.leader_origin is not None:
            ex, ey, _ = geodetic_to_enu(self.leader_origin, tel.lat_deg, tel.lon_deg)
            x, y = float(ex), float(ey)
        speed, heading = self.leader.leader_command(now - self._t_start, float(x), float(y), own.heading, own.speed)
        return float(speed), wrap_angle(float(heading) - own.heading), "coop", ""

    def _gap(self, wall: float) -> tuple[float, float]:
        """Measured gap to the immediate predecessor (m, centre to centre) and its closing
        speed (m/s): the member's estimate from its messages (bounded dead-reckoning, as in
        simulation); NaN and 0 for the leader or when unknown."""
        est = None if self.is_leader else self.member.gap_estimate(wall)
        return (math.nan, 0.0) if est is None else est

    def _maybe_reconnect(self, now: float) -> None:
        """A lost connection (TCP EOF, serial error) is reopened every 2 s, without
        blocking the tick (``reconnect(0)``: the link opens it in the background)."""
        if not self.link.lost or now - self._t_reconnect < 2.0:
            return
        self._t_reconnect = now
        try:
            self.link.reconnect(0.0)
        except Exception as exc:  # noqa: BLE001 - keep trying
            log.info("reconnect failed: %s", exc)

    def _ranging(self, tel: Telemetry, now: float) -> tuple[float, float] | None:
        """(range, range rate) to the vehicle ahead for the staleness ladder, centre to
        centre (m, m/s) as in ``sim``: the rangefinder reads from the front bumper to the
        predecessor's rear, so half of each length is added. None without a fresh reading."""
        r, rate = tel.range_m, tel.range_rate_mps
        if self.is_leader or not (math.isfinite(r) and math.isfinite(rate)):
            return None
        if now - tel.t_range > RANGE_MAX_AGE_S:
            return None
        lengths = self.member.lengths
        i = self.options.vehicle_id
        return r + 0.5 * (lengths[i] + lengths[i - 1]), rate

    def _track_broadcast(self, known: bool, wall: float) -> None:
        """Announce and record when broadcasting stops (autopilot link lost) and resumes."""
        if known == self._broadcasting:
            return
        self._broadcasting = known
        vid = self.options.vehicle_id
        if known:
            self._broadcast_pauses[-1][1] = wall
            self.on_status(f"vehicle {vid}: autopilot link back: broadcasting the own state again")
        else:
            self._broadcast_pauses.append([wall, None])
            self.on_status(f"vehicle {vid}: autopilot link lost: not broadcasting the own state "
                           "(it is unknown now)")

    @staticmethod
    def _brake_time_s(v0: float) -> float:
        """How long stop setpoints are streamed before HOLD at most (s): braking from
        ``v0`` m/s at 1 m/s² (ArduPilot's ATC_ACCEL_MAX) plus a second, 1-6 s."""
        return min(6.0, 1.0 + abs(v0))

    def _log_row(self, wall: float, own: VehicleState, tel: Telemetry, speed: float, change: float,
                 mode: str, gap: float, sent: bool) -> None:
        if not self.recorder.recording:
            return
        m = self.member
        self.recorder.row({
            "t_s": wall, "vehicle_id": self.options.vehicle_id, "x_m": own.x, "y_m": own.y,
            "lat_deg": tel.lat_deg, "lon_deg": tel.lon_deg, "speed_mps": own.speed,
            "heading_rad": own.heading, "accel_mps2": own.accel,
            "cmd_speed_mps": speed if sent else math.nan,
            "cmd_heading_change_rad": change if sent else math.nan,
            "mode": mode, "gap_m": gap, "desired_gap_m": self.frame.desired_gap_m,
            "spacing_error_m": self.frame.spacing_error_m, "msgs_sent": m.msgs_sent,
            "msgs_received": self._delivered(), "msgs_lost": self.v2v.counters.lost,
            "pred_msg_age_s": self.frame.pred_msg_age_s, "length_m": m.lengths[self.options.vehicle_id],
            "msgs_kept": m.msgs_received,
            "loop_overruns": self._timer.overruns if self._timer else 0,
            "telemetry_age_s": max(wall - own.t, 0.0),
        })

    def _delivered(self) -> int:
        """Vehicle messages the V2V link delivered (aborts are not traffic)."""
        c = self.v2v.counters
        return int(c.received - c.aborts)

    def _status_line(self, now: float, own: VehicleState, mode: str, gap: float) -> None:
        p = self.options.status_period_s
        if p <= 0 or now - self._t_status < p:
            return
        self._t_status = now
        m = self.member
        parts = [f"vehicle {self.options.vehicle_id}", mode, f"v {own.speed:4.2f} m/s"]
        if not self.is_leader:
            parts.append(f"gap {gap:5.2f} m (want {self.frame.desired_gap_m:4.1f})")
            parts.append(f"age {self.frame.pred_msg_age_s:4.2f} s")
        parts.append(f"tx {m.msgs_sent} rx {m.msgs_received}")
        self.on_status(" | ".join(parts))

    def _finish(self, reason: str, code: int = 0) -> None:
        """Stop, HOLD, flush and close the log, write metadata. Never raises."""
        o = self.options
        took_over = self.failsafes.took_over or self.link.pilot_took_over
        if self.commanding and self._armed_by_us and not took_over:
            try:
                self._brake_to_rest()
                self.link.hold(2.0)
            except Exception as exc:  # noqa: BLE001 - the log must still be saved
                log.warning("vehicle %d: HOLD at exit failed: %s", o.vehicle_id, exc)
        elif self.commanding and self._arming:
            # Interrupted while arming (a signal, a refusal, a lost mode): it may have armed
            # meanwhile. Standing still, so HOLD and disarm; never armed without HOLD.
            for step in (self.link.hold, self.link.disarm):
                try:
                    step(0.0)
                except Exception as exc:  # noqa: BLE001
                    log.warning("vehicle %d: HOLD/disarm after arming failed: %s", o.vehicle_id, exc)
        elif self.commanding and took_over and self._t_start is None and self._armed_by_us:
            self._disarm_if_at_rest()
        if self.recorder.recording:
            self.recorder.close(self._metadata(reason, code))
        for closer in (self.v2v.close, self.link.close):
            try:
                closer()
            except Exception:  # noqa: BLE001
                pass
        self.on_status(f"vehicle {o.vehicle_id}: stopped ({reason})")

    def _brake_to_rest(self) -> None:
        """Stream stop setpoints until the vehicle is slower than ``HOLD_BELOW_MPS`` (at
        most ``_brake_time_s``), while the autopilot link is fresh."""
        tel = self._tel
        v0 = abs(tel.state.speed) if tel is not None else 0.0
        end = self.clock() + self._brake_time_s(v0)
        period = 1.0 / self.options.rate_hz
        while True:
            if not self.link.stop_motion():
                return  # taken over, or a PX4 stream that must not resume
            got = self.link.poll()
            tel = got or tel
            now = self.clock()
            if tel is None or abs(tel.state.speed) < HOLD_BELOW_MPS or now >= end:
                return
            if not self.failsafes.watchdog.fresh(now, tel.t_telemetry, tel.t_heartbeat,
                                                 not self.link.lost):
                return
            self.sleep(period)

    def _disarm_if_at_rest(self) -> None:
        """A takeover before the convoy drove (ArduPilot's RC mode switch setting MANUAL
        after GUIDED, say) must not leave the vehicle armed and forgotten: disarm it if it
        stands still, else say loudly that it is armed in someone else's hands."""
        vid = self.options.vehicle_id
        tel = self.link.poll() or self._tel
        mode = tel.mode if tel is not None else "?"
        if tel is not None and abs(tel.state.speed) < HOLD_BELOW_MPS:
            try:
                self.link.disarm(2.0)
                self.on_status(f"vehicle {vid}: disarmed (taken over in {mode} before the convoy drove)")
                return
            except Exception as exc:  # noqa: BLE001
                log.warning("vehicle %d: disarm failed: %s", vid, exc)
        self.on_status(f"vehicle {vid}: WARNING: left ARMED in {mode} (taken over before the convoy drove)")

    def _metadata(self, reason: str, code: int = 0) -> dict[str, Any]:
        """The run's metadata (``vehicle_N.json``)."""
        o = self.options
        wall0 = self.wall() - self.clock()  # maps monotonic event times to the shared clock
        meta = {
            "kind": "deploy",
            "vehicle_id": o.vehicle_id,
            "n_vehicles": self.convoy.n_vehicles,
            "convoy": self.convoy.name,
            "scenario": self.convoy.scenario,
            "policy": self.policy.name,
            "rate_hz": o.rate_hz,
            "dry_run": o.dry_run,
            "passive": o.passive,
            "autopilot": _safe(lambda: self.link.autopilot),
            "telemetry_rates_hz": self.link.telemetry_rates,
            "v2v": _safe(lambda: self.v2v.metadata) or {},
            "t_begin_s": self._t_begin_wall,
            "t_start_s": self._t_start_wall,
            "t_end_s": self.wall(),
            "exit_reason": reason,
            "exit_code": code,
            "takeover_reason": self.link.takeover_reason or None,
            "broadcast_paused": [
                {"from_s": a, "to_s": b, "why": "autopilot link lost"} for a, b in self._broadcast_pauses
            ],
            "ticks": self._timer.ticks if self._timer else 0,
            "overruns": self._timer.overruns if self._timer else 0,
            "late_ticks": self._timer.late_ticks if self._timer else 0,
            "max_tick_late_s": self._timer.max_late_s if self._timer else 0.0,
            "v2v_counters": _safe(lambda: asdict(self.v2v.counters)),
            "policy_errors": self.failsafes.policy_errors,
            "failsafe_events": [{"t_s": wall0 + t, "reason": r} for t, r in self.failsafes.events],
            "msgs_sent": self.member.msgs_sent,
            "msgs_received": self._delivered(),
            "msgs_kept": self.member.msgs_received,
            "msgs_lost": self.v2v.counters.lost,
            **self.metadata_extra,
        }
        return meta


def _safe(fn: Callable[[], Any]) -> Any:
    try:
        return fn()
    except Exception:  # noqa: BLE001
        return None
