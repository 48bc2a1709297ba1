"""The real-time runner behind ``openconvoy deploy``: the simulator's tick, on a vehicle.

Each tick, at a fixed rate (20 Hz by default; clock and sleep injected), steps 1 to 4 being
``core.tick.tick``, the simulator's rules, with the V2V (``bridge.exchange``) as its radio:

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

The parts: ``bridge.vehicle`` (connect, arm, setpoints and HOLD, the safe finish),
``bridge.convoystart`` (the wait for the convoy), ``bridge.leaderdrive`` (the leader's
commands, the run's length), ``bridge.exchange`` (V2V send and receive), ``bridge.intent``
(the policy's or the leader's command), ``bridge.safetygate`` (the failsafes' verdict),
``bridge.runlog`` (log rows, status lines, metadata); ``DeployRunner`` schedules them and
owns the tick.
"""

from __future__ import annotations

import logging
import math
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Protocol

from openconvoy.bridge.convoystart import ConvoyStart
from openconvoy.bridge.exchange import RECEIVE_BUDGET, Exchange
from openconvoy.bridge.failsafes import (
    Envelope,
    Failsafes,
    LinkWatchdog,
    LoopTimer,
)
from openconvoy.bridge.intent import ControllerIntent
from openconvoy.bridge.leaderdrive import FINISH_TIMEOUT_S, LeaderDriver, LeaderDriving
from openconvoy.bridge.limits import MIN_RATE_HZ
from openconvoy.bridge.link import VehicleLink, VehicleLinkError
from openconvoy.bridge.runlog import EXTRA_COLUMNS, RunLog
from openconvoy.bridge.safetygate import SafetyGate
from openconvoy.bridge.vehicle import (
    HOLD_BELOW_MPS,
    HOLD_MODES,
    StopRequested,
    VehicleHandler,
    brake_time_s,
)
from openconvoy.comms.geodesy import Origin
from openconvoy.convoy import ConvoyConfig
from openconvoy.core import tick as member_tick
from openconvoy.core.errors import ConfigError, OpenConvoyError
from openconvoy.core.member import ConvoyMember, Frame, member_config_for
from openconvoy.core.plans import Plan, PlanningPolicy, braking_plan
from openconvoy.core.policy import ConvoyPolicy, act_time_report, as_convoy_policy
from openconvoy.core.spacing import SpacingConfig
from openconvoy.core.state import VehicleState, wrap_angle

log = logging.getLogger(__name__)

__all__ = [  # the parts' names stay importable from here
    "EXTRA_COLUMNS",
    "FINISH_TIMEOUT_S",
    "RECEIVE_BUDGET",
    "HOLD_BELOW_MPS",
    "HOLD_MODES",
    "DeployRunner",
    "LeaderDriver",
    "RunResult",
    "RunnerOptions",
    "StopRequested",
    "TickTiming",
    "V2VEndpoint",
    "envelope_from",
]


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
        stay_armed: leave the vehicle armed in HOLD at the end (``--stay-armed``); by
            default a run ends with its vehicle at rest and disarmed.
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
    stay_armed: bool = False

    def __post_init__(self) -> None:
        # Checked here too (the CLI checks its flags): a NaN rate or timeout would busy-loop
        # setpoints to the autopilot or wait forever.
        if not (math.isfinite(self.rate_hz) and MIN_RATE_HZ <= self.rate_hz <= 100.0):
            raise ConfigError(
                f"control rate (--rate, or the policy's control_rate_hz): {self.rate_hz!r} Hz "
                f"is out of range; allowed: {MIN_RATE_HZ:g}..100 Hz"
            )
        for what, value, hi in (
            ("--connect-timeout, s", self.connect_timeout_s, 86400.0),
            ("--arm-timeout, s", self.arm_timeout_s, 86400.0),
            ("--duration, s", 1.0 if self.duration_s is None else self.duration_s, 7 * 86400.0),
        ):
            if not (math.isfinite(value) and 0.0 < value <= hi):
                raise ConfigError(
                    f"{what}: {value!r} is out of range; allowed: a finite number in (0, {hi:g}]"
                )
        if self.passive and self.vehicle_id != 0:
            raise ConfigError(
                "--passive is for the leader (vehicle 0): followers are driven by the policy"
            )


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

    return make_scenario(
        convoy.scenario, presets=[vehicle_preset(v) for v in convoy.vehicles]
    ).spacing


def bind_planning(
    policy: ConvoyPolicy, convoy: ConvoyConfig, vehicle_id: int
) -> PlanningPolicy | None:
    """A model-based policy predicts with its vehicle's preset (``bind_vehicle``, as in
    ``sim``); a planning one (``core.plans``) is returned for the plan exchange."""
    from openconvoy.envs.vehicles import vehicle_preset

    bind = getattr(policy, "bind_vehicle", None)
    if bind is not None and 0 <= vehicle_id < len(convoy.vehicles):
        bind(vehicle_preset(convoy.vehicles[vehicle_id]))
    return policy if isinstance(policy, PlanningPolicy) else None


def leader_preset(convoy: ConvoyConfig) -> Any:
    """The leader's vehicle preset: the model of the plan a driven leader shares."""
    from openconvoy.envs.vehicles import vehicle_preset

    return vehicle_preset(convoy.vehicles[0])


def top_speed(convoy: ConvoyConfig, vehicle_id: int) -> float:
    """The vehicle's preset top speed (m/s): the top of its action space, as in ``sim``."""
    from openconvoy.envs.vehicles import vehicle_preset

    return vehicle_preset(convoy.vehicles[vehicle_id]).max_speed_mps


def envelope_from(convoy: ConvoyConfig, vehicle_id: int | None = None) -> Envelope:
    """The safety envelope a convoy config asks for; with ``vehicle_id``, the braking-aware
    gap rule from that vehicle's preset (margin ``[safety] gap_margin_m`` or its default);
    the leader's is to the convoy's last vehicle, the one a lapping leader meets (D49)."""
    s = convoy.safety
    braking, ego_len, pred_len = None, 0.0, 0.0
    if vehicle_id is not None and convoy.n_vehicles > 1:
        from openconvoy.core.safety import for_vehicle
        from openconvoy.envs.vehicles import vehicle_preset

        ego, pred = (
            vehicle_preset(convoy.vehicles[vehicle_id]),
            vehicle_preset(convoy.vehicles[vehicle_id - 1 if vehicle_id > 0 else -1]),
        )
        braking = for_vehicle(
            ego.decel_max_mps2, ego.actuation_delay_s, ego.speed_lag_s, ego.length_m, s.gap_margin_m
        )
        ego_len, pred_len = ego.length_m, pred.length_m
    return Envelope(
        speed_cap_mps=s.speed_cap_mps,
        geofence_radius_m=s.geofence_radius_m,
        min_gap_m=s.min_gap_m,
        max_msg_age_s=s.max_msg_age_s,
        braking=braking,
        ego_length_m=ego_len,
        pred_length_m=pred_len,
    )


def make_member(
    policy: ConvoyPolicy,
    convoy: ConvoyConfig,
    vehicle_id: int,
    spacing: SpacingConfig | None,
    lengths: list[float] | None,
    decels: list[float] | None,
) -> ConvoyMember:
    """The convoy member, configured as in ``sim``: the policy's member config, or for a
    policy without one ``spacing`` (default: the convoy scenario's; ``member_config_for``)."""
    config = policy.member_config
    if config is None and spacing is None:
        spacing = scenario_spacing(convoy)
    member_config = member_config_for(config, spacing or SpacingConfig())
    return ConvoyMember(vehicle_id, convoy.n_vehicles, member_config, lengths, decels)


def gap_ahead(member: ConvoyMember, wall: float) -> tuple[float, float]:
    """Measured gap to the immediate predecessor (m, centre to centre) and its closing speed
    (m/s): the member's estimate from its messages (bounded dead-reckoning, as in
    simulation); for the leader, to the nearest member in its path (``path_gap``: a
    closed track's tail, D49); NaN and 0 when unknown."""
    if member.vehicle_id == 0:
        ahead = member.path_gap(wall)
        return (math.nan, 0.0) if ahead is None else (ahead[0], ahead[1])
    est = member.gap_estimate(wall)
    return (math.nan, 0.0) if est is None else est


def great_circle_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Distance (m) between two WGS-84 points on a sphere of the mean Earth radius
    (haversine; within 0.5 % of the ellipsoid)."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2.0 * 6_371_008.8 * math.asin(min(1.0, math.sqrt(h)))


def _distance_text(d: float) -> str:
    """``d`` metres as a person says it: "212 m", "7,512 km"."""
    return f"{d:,.0f} m" if d < 10_000 else f"{d / 1000:,.0f} km"


def failure_code(
    failsafes: Failsafes, started: bool, autopilot_failsafe: bool, uncommanded: str = ""
) -> int:
    """1 when the run ended by a failsafe, a lost autopilot link, a takeover before the
    convoy ``started``, an autopilot failsafe or uncommanded motion while held; 0 when it
    completed or a person stopped it (signal, ``abort``) with nothing of that kind on the
    way."""
    if failsafes.latched or failsafes.watchdog.was_lost or uncommanded:
        return 1
    if failsafes.took_over and (not started or autopilot_failsafe):
        return 1
    return 0


class DeployRunner:
    """One vehicle's real-time loop. ``run()`` connects, arms, loops and returns a
    ``RunResult``; ``request_stop(name)`` (signal handlers) ends it cleanly.

    Its parts (see the module docstring): ``vehicle``, ``start_gate``, ``leading``,
    ``exchange``, ``intent``, ``gate`` and ``runlog``.

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
            raise ConfigError(
                f"vehicle id {options.vehicle_id} not in this convoy of {n} vehicles (0..{n - 1})"
            )
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
        self.member = make_member(self.policy, convoy, options.vehicle_id, spacing, lengths, decels)
        self._planning = bind_planning(self.policy, convoy, options.vehicle_id)
        self.bounds = bounds or member_tick.ActionBounds.float32(
            top_speed(convoy, options.vehicle_id)
        )
        self.frame: Frame = Frame(math.nan, self.member.layout.zeros())
        """The member's latest frame (its observation and derived values)."""
        self.failsafes = Failsafes(
            envelope=envelope or envelope_from(convoy, options.vehicle_id),
            watchdog=LinkWatchdog(link.telemetry_timeout_s, link.heartbeat_timeout_s),
        )
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.metadata_extra = dict(metadata or {})
        self.timings: list[TickTiming] = []
        self._init_run_state()

    def _init_run_state(self) -> None:
        """The run's parts and what one run accumulates (stop requests, timers, broadcast
        bookkeeping)."""
        o = self.options
        self._stop_requested = ""
        self._ending = ""  # why the run ends, while the loop brakes to rest
        # The lambdas read ``self.sleep`` / ``self.on_status`` at call time (tests swap them).
        status = lambda line: self.on_status(line)  # noqa: E731
        self.vehicle = VehicleHandler(
            self.link,
            self.failsafes.watchdog,
            vehicle_id=o.vehicle_id,
            rate_hz=o.rate_hz,
            commanding=self.commanding,
            clock=self.clock,
            sleep=lambda s: self.sleep(s),
            on_status=status,
            check_stop=self._check_stop,
            stay_armed=o.stay_armed,
            on_event=lambda why: self.failsafes.events.append((self.clock(), why)),
        )
        self.start_gate = ConvoyStart(
            o.vehicle_id,
            self.convoy.n_vehicles,
            self.member.rx.keeps,
            leader_waits=not o.passive and o.leader_waits_for_convoy,
            wait_s=o.convoy_wait_s,
            clock=self.clock,
            on_start=lambda: status(f"vehicle {o.vehicle_id}: convoy complete, starting"),
            refusal=self._start_refusal,
            on_status=status,
        )
        self.leading = LeaderDriving(
            self.leader,
            is_leader=self.is_leader,
            passive=o.passive,
            commanding=self.commanding,
            duration_s=o.duration_s,
            rate_hz=o.rate_hz,
            origin=self.leader_origin,
            preset=leader_preset(self.convoy) if self.is_leader and self._planning else None,
        )
        self.exchange = Exchange(
            self.member, self.v2v, self.start_gate, rate_hz=o.rate_hz, on_status=status
        )
        self.runlog = RunLog(self.log_dir, o.vehicle_id, o.status_period_s, status)
        self.intent = ControllerIntent(
            self.member,
            self.bounds,
            self.leading,
            self.start_gate,
            self.failsafes,
            period_s=1.0 / o.rate_hz,
            clock=self.clock,
        )
        self.gate = SafetyGate(
            self.failsafes, self.link, self.member, self.exchange, lambda: self.commanding, status
        )
        self.timer: LoopTimer | None = None
        self._late_periods = 0.0
        self._sent_last = False  # the last tick's setpoint went out
        self.t_begin_wall = self.wall()

    # ------------------------------------------------------------------ control

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the loop to stop, HOLD, flush the log and return (safe from signal handlers)."""
        self._stop_requested = reason

    @property
    def decision(self) -> member_tick.Decision | None:
        """The member's latest decision (None for a leader, or while waiting to start)."""
        return self.intent.decision

    @property
    def commanding(self) -> bool:
        """Whether this run sends setpoints at all (not dry-run, not passive)."""
        return not (self.options.dry_run or self.options.passive)

    # ------------------------------------------------------------------ run

    def start(self) -> None:
        """Connect, wait for telemetry, arm (unless dry-run/passive), open the log."""
        o = self.options
        self.vehicle.connect(o.connect_timeout_s)
        self._check_inside_fence()
        self.runlog.recorder.open()  # before arming: a log that cannot be written refuses
        if self.commanding and not self._stop_requested:
            self.vehicle.arm(o.arm_timeout_s)
        self.policy.reset(o.seed)
        self.leading.reset(o.seed)
        self.on_status(
            f"vehicle {o.vehicle_id}: ready"
            + (" (dry run: no setpoints)" if o.dry_run else "")
            + (" (passive: broadcasting only)" if o.passive else "")
        )

    def _check_inside_fence(self) -> None:
        """Refuse (before arming) a vehicle that stands outside the geofence, naming how
        far outside it is (D64: a vehicle 7,500 km from the convoy's origin armed, then
        latched ``geofence``)."""
        tel = self.vehicle.tel
        radius = self.failsafes.envelope.geofence_radius_m
        if tel is None or not self.commanding:
            return
        if math.hypot(tel.state.x, tel.state.y) <= radius:  # as the fence itself measures
            return
        lat0, lon0 = self.origin.lat_deg, self.origin.lon_deg
        d = great_circle_m(lat0, lon0, tel.lat_deg, tel.lon_deg)
        if d > radius:
            raise ConfigError(
                f"vehicle {self.options.vehicle_id} is {_distance_text(d)} from the convoy's "
                f"origin ({lat0:.6f}, {lon0:.6f}), outside the {radius:g} m geofence "
                f"(it stands at {tel.lat_deg:.6f}, {tel.lon_deg:.6f}): not arming. Check the "
                "convoy's origin and the vehicle's position"
            )

    def run(self) -> RunResult:
        """Start, loop until the run ends, stop safely. Never leaves the vehicle moving."""
        reason = "ended"
        code = 0
        try:
            self.start()
            reason = self._loop()
        except StopRequested as exc:
            reason = str(exc)
        except KeyboardInterrupt:
            reason = "SIGINT"
        except (VehicleLinkError, TimeoutError) as exc:  # the vehicle said no, or nothing
            reason = f"error: {exc}"
            code = 1
            log.error("vehicle %d: %s", self.options.vehicle_id, exc)
        except OpenConvoyError as exc:  # refused before arming (the log, the geofence)
            reason = f"refused: {exc}"
            code = 2
            self.on_status(f"vehicle {self.options.vehicle_id}: refused: {exc}")
        except Exception as exc:  # a runner bug must not leave the vehicle moving
            reason = f"error: {exc}"
            code = 1
            log.error("deploy loop failed:\n%s", traceback.format_exc())
        finally:
            self._finish(reason, code)
            code = (
                code
                or failure_code(
                    self.failsafes,
                    self.start_gate.t_start is not None,
                    self.link.modes.failsafe_took_over,
                    self.vehicle.uncommanded,
                )
                or (1 if self.runlog.recorder.failed else 0)
                or (1 if self.start_gate.refused else 0)
            )
            self._close(reason, code)
        return RunResult(
            exit_code=code,
            reason=reason,
            ticks=self.timer.ticks if self.timer else 0,
            overruns=self.timer.overruns if self.timer else 0,
            policy_errors=self.failsafes.policy_errors,
            t_start_s=self.start_gate.t_start_wall,
            events=list(self.failsafes.events),
        )

    def _loop(self) -> str:
        """Tick at the control rate until a tick says why the run ends, then on (stop
        setpoints, log rows and broadcasts) until the vehicle is at rest (``_braked``)."""
        period = 1.0 / self.options.rate_hz
        self.timer = timer = LoopTimer(period, self.clock())
        ending, t_end, v_end = "", math.nan, 0.0
        while True:
            wait = timer.wait_time(self.clock())
            if wait > 0:
                self.sleep(wait)
            t_tick = self.clock()
            self._late_periods = timer.begin(t_tick) / period
            done = self.tick(t_tick)
            if done and not ending:
                ending, t_end = done, t_tick
                self._ending = done  # the next ticks stop the vehicle (the gate's STOP)
                v_end = abs(self.vehicle.tel.state.speed) if self.vehicle.tel else 0.0
            if ending and self._braked(t_tick, t_end, v_end):
                return ending

    def _braked(self, now: float, t_end: float, v_end: float) -> bool:
        """After the tick that ended the run (at ``t_end``, at ``v_end`` m/s): whether the
        vehicle is at rest, or nothing more can be done from here (not commanding, taken
        over, the autopilot link stale, no stop setpoint accepted by the link (PX4's stream
        ended), or the braking time of
        ``vehicle.brake_time_s`` over). Until then the loop goes on stopping, logging and
        broadcasting, so that a run ended by a signal or an abort logs its braking and its
        followers see it stop."""
        tel = self.vehicle.tel
        if (
            tel is None
            or not (self.commanding and self.vehicle.armed_by_us)
            or self.failsafes.took_over
            or not self._sent_last
            or abs(tel.state.speed) < HOLD_BELOW_MPS
            or now - t_end >= brake_time_s(v_end)
        ):
            return True
        return not self.failsafes.watchdog.fresh(
            now, tel.t_telemetry, tel.t_heartbeat, not self.link.lost
        )

    def _start_refusal(self) -> str:
        """The V2V link's reason not to start ("" = none; ``comms.v2v.V2V.start_refusal``)."""
        refusal = getattr(self.v2v, "start_refusal", None)
        return "" if refusal is None else str(refusal(self.wall()))

    def _check_stop(self) -> None:
        if self._stop_requested:
            raise StopRequested(self._stop_requested)

    # ------------------------------------------------------------------ one tick

    def _own_plan(self, mode: str, own: VehicleState, now: float, wall: float) -> Plan | None:
        """The plan to share: a driven leader's driver's (``LeaderDriving.plan``, as the
        simulated leader shares), else the policy's, while its commands go out (``coop``);
        else braking to rest at the vehicle's limit, which is what it does instead."""
        assert self._planning is not None
        if self.is_leader:
            mpc = getattr(self._planning, "mpc", None)
            plan = self.leading.plan(own, now, self.start_gate.t_start, wall, mpc)
        else:
            plan = self._planning.plan()
        if mode == "coop" or plan is None:
            return plan
        decel = self.member.decels[self.options.vehicle_id]
        return braking_plan(self.options.vehicle_id, wall, own.speed, decel, plan)

    def _started(self, now: float, wall: float) -> bool:
        """Whether the convoy started, at monotonic ``now`` and shared-clock ``wall`` (s),
        asked once a tick after receiving (who was heard) and before the policy acts, which
        then sees the plans heard (``core.plans``)."""
        waiting = self.start_gate.update(now, wall, self.timer.start if self.timer else None)
        if self._planning is not None:
            self._planning.observe_plans(self.exchange.plans.plans, self.options.vehicle_id, wall)
        return not waiting

    def tick(self, now: float) -> str:
        """One control tick at monotonic time ``now``. Returns "" to go on, else why the run ends."""
        tel, t_polled = self.vehicle.read(now)
        wall = self.wall()
        own = replace(tel.state, vehicle_id=self.options.vehicle_id)
        known = self.failsafes.watchdog.fresh(
            now, tel.t_telemetry, tel.t_heartbeat, not self.link.lost
        )
        self.exchange.track_broadcast(known, wall)
        # The member's tick, the simulator's (τ, send, receive, ρ, act, decide), and what
        # the controller wants (the member's decision, or the leader's driver) ...
        ticked, want = self.intent.tick(
            self.policy,
            tel,
            own,
            known,
            self.exchange,
            (now, wall),
            partial(self._started, now, wall),
        )
        self.frame = ticked.frame
        waiting = not ticked.started
        gap, closing = gap_ahead(self.member, wall)
        heading_cmd = wrap_angle(own.heading + want[1])
        # ... and what the failsafes and the envelope let through.
        verdict = self.gate.decide(
            (now, wall),
            tel,
            own,
            want,
            waiting=waiting,
            heading_cmd=heading_cmd,
            gap=(gap, closing),
            stop_requested=self._stop_requested,
            late_periods=self._late_periods,
            ending=self._ending,
        )
        speed, heading_cmd, mode = self.gate.let_through(verdict, want, own, heading_cmd)
        if self._planning is not None:
            self.exchange.offer_plan(self._own_plan(mode, own, now, wall))
        t_sent = self.vehicle.actuate(now, tel, own, verdict, speed, heading_cmd)
        self._sent_last = not math.isnan(t_sent)
        if self.options.record_timing:
            self.timings.append(TickTiming(now, t_polled, t_sent, tel.t_telemetry))
        self.runlog.row(
            self,
            wall,
            own,
            tel,
            speed,
            wrap_angle(heading_cmd - own.heading),
            mode,
            gap,
            sent=self.commanding and not math.isnan(t_sent),
            valid=known,
        )  # what really went out
        self.runlog.status(self, now, own, mode, gap, valid=known)
        if self.runlog.recorder.failed and not verdict.exit:
            return f"log write failed ({self.runlog.recorder.failed})"
        return verdict.reason if verdict.exit else self._end_reason(now, own)

    # ------------------------------------------------------------------ tick phases

    def _end_reason(self, now: float, own: VehicleState) -> str:
        """Why the run ends after this tick ("" = it goes on): a takeover before the convoy
        drove, or the duration (a scenario-driven leader first brakes to rest)."""
        t_start = self.start_gate.t_start
        if self.failsafes.took_over and t_start is None and self.commanding:
            why = self.link.modes.takeover_reason or "a mode change we did not ask for"
            return f"pilot took over before the convoy drove: {why}"
        if self.start_gate.refused:
            return f"convoy start refused: {self.start_gate.refused}"
        if t_start is None:
            return ""
        if self.exchange.leader_complete and not self.is_leader:
            return "the leader completed its scenario"
        if self.leading.over(now, t_start, own.speed):
            if self.is_leader and not self.options.passive:
                self.exchange.announce_complete(self.wall())
            return "duration reached"
        return ""

    # ------------------------------------------------------------------ helpers

    def _finish(self, reason: str, code: int = 0) -> None:
        """Stop, HOLD and disarm the vehicle (``VehicleHandler.secure``). Never raises."""
        took_over = self.failsafes.took_over or self.link.modes.pilot_took_over
        try:
            self.vehicle.secure(
                took_over,
                drove=self.start_gate.t_start is not None,
                autopilot_failsafe=self.link.modes.failsafe_took_over,
            )
        except Exception:  # noqa: BLE001 - the log and the sockets must still be closed
            log.error(
                "vehicle %d: securing failed:\n%s", self.options.vehicle_id, traceback.format_exc()
            )

    def _close(self, reason: str, code: int) -> None:
        """Flush and close the log, write metadata, close V2V and the link. Never raises."""
        try:
            self.runlog.close(self, reason, code)
        except Exception:  # noqa: BLE001
            log.error(
                "vehicle %d: closing the log failed:\n%s",
                self.options.vehicle_id,
                traceback.format_exc(),
            )
        for closer in (self.v2v.close, self.link.close):
            try:
                closer()
            except Exception:  # noqa: BLE001
                pass
        if self.intent.guard is not None:  # the policy's act time against the period
            self.on_status(
                f"vehicle {self.options.vehicle_id}: "
                + act_time_report(self.intent.guard.times, 1.0 / self.options.rate_hz)
            )
        self.on_status(f"vehicle {self.options.vehicle_id}: stopped ({reason})")
