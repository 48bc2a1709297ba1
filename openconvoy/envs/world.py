"""ConvoyWorld: the simulated convoy behind ``ConvoyEnv`` — plant, channel, members,
sensors and faults — ticking the members through ``core.tick`` as a vehicle does.

One tick (``dt`` s): ``decide`` takes every follower's action through its member
(``core.tick.decide``: finite check, clip, staleness ladder with the ranging sensor's
reading), then the braking-aware emergency stop and a refused action's stop (both latched,
mode ``failsafe``), the leader's scenario command and the faults; ``advance`` records the
tick (``TickRecord``), steps the plant and senses at the new time: every member's own
state (optional GPS noise, ``envs.gps``: counter-based), τ, the channel, forged messages, ρ and its ``Frame``.

Safety, as on vehicles: a follower whose braking-aware gap rule fires (``core.safety``:
the gap between bumpers, less what braking at its limit from the closing speed takes, is
below the margin; the gap from its ranging sensor, else from its member's estimate of
the predecessor) stops for the rest of the episode; ``safety_events`` says when and why.
Faults (``core.faults``: ``halt``, ``silent``, ``dead``, ``forge``) override a vehicle's
setpoints with a stop at its braking limit and/or mute its broadcasts from their time on,
or forge messages in its name.
"""

from __future__ import annotations

import gc
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.comms.loss import LossConfig
from openconvoy.core import tick as member_tick
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_faults
from openconvoy.core.member import ConvoyMember, Frame, MemberConfig
from openconvoy.core.ranging import range_and_rate
from openconvoy.core.safety import (
    BLIND,
    CLEAR,
    TOO_CLOSE,
    BrakingGap,
    bumper_gap,
    for_vehicle,
    verdict,
)
from openconvoy.core.state import VehicleState
from openconvoy.envs.channel import Channel, advance_state
from openconvoy.envs.forgery import Authentication
from openconvoy.envs.gps import gps_key, gps_noise, vehicle_states
from openconvoy.envs.plans import PlanExchange
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.ranging_noise import ranging_key, ranging_normals
from openconvoy.envs.scenarios import Scenario
from openconvoy.envs.vehicles import VehiclePreset
from openconvoy.logs import TickSnapshot

Ranging = member_tick.Ranging


@contextmanager
def _collection_paused() -> Iterator[None]:
    """CPython's cyclic garbage collector off for the block (as it was after): the first
    sense of a long convoy makes an object per kept link (N²/2 with all predecessors,
    all of them kept), and every collection the allocations trigger rescans them all:
    13 of 17 s of a 1,000-follower reset. Nothing in the block makes garbage cycles."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


@dataclass(frozen=True, slots=True)
class Truth:
    """Ground truth of every vehicle (leader first) at one tick: ENU position (m), speed
    (m/s), heading (rad), acceleration (m/s²), yaw rate (rad/s)."""

    x: list[float]
    y: list[float]
    speed: list[float]
    heading: list[float]
    accel: list[float]
    yaw_rate: list[float]

    @classmethod
    def of(cls, plant: BicyclePlant) -> Truth:
        return cls(
            plant.x.tolist(),
            plant.y.tolist(),
            plant.speed.tolist(),
            plant.heading.tolist(),
            plant.accel.tolist(),
            plant.yaw_rate.tolist(),
        )


@dataclass(frozen=True, slots=True)
class TickRecord:
    """What one tick's log rows report (``ConvoyWorld.snapshot`` makes them a
    ``logs.TickSnapshot``): time (s), the truth, the commands applied from it and the
    modes, ground-truth gaps to the predecessor (NaN for the leader), the members'
    frames, and the message counters (cumulative) of every vehicle."""

    t: float
    truth: Truth
    cmd_speed: list[float]
    cmd_heading_change: list[float]
    modes: list[str]
    gaps: list[float]
    frames: list[Frame]
    msgs_sent: list[int]
    msgs_received: list[int]
    msgs_lost: list[int]
    extra: dict[str, list[Any]] = field(default_factory=dict)


class ConvoyWorld:
    """The simulated convoy of ``scenario``'s vehicles with ``member_config`` members.

    ``dt`` (s) is the control and plant period; see ``ConvoyEnv`` for the other arguments.
    """

    record: TickRecord | None
    """The last completed tick (None right after ``reset``)."""
    truth: Truth
    frames: list[Frame]
    gaps: list[float]
    desired: list[float]
    collided: list[bool]
    rx: list[int]
    lost: list[int]
    safety_events: list[tuple[float, int, str]]
    """(t s, vehicle, reason): faults injected, refused actions and emergency stops."""

    def __init__(
        self,
        scenario: Scenario,
        member_config: MemberConfig,
        loss: LossConfig,
        dt: float,
        gps_noise_m: float = 0.0,
        faults: Sequence[Fault] = (),
        gap_margin_m: float | None = None,
        emergency_stop: bool = True,
        auth: bool = True,
        plant_presets: Sequence[VehiclePreset] | None = None,
    ) -> None:
        self.scenario = scenario
        self.presets = tuple(scenario.presets)
        self.n_vehicles = n = len(self.presets)
        self.dt = dt
        self.gps_noise_m = gps_noise_m
        self.lengths = [p.length_m for p in self.presets]
        self.widths = [p.width_m for p in self.presets]
        self._half_sum = [0.5 * (a + b) for a, b in zip(self.lengths[1:], self.lengths[:-1])]
        decels = [p.decel_max_mps2 for p in self.presets]
        self.members = [ConvoyMember(i, n, member_config, self.lengths, decels) for i in range(n)]
        self.faults = tuple(faults)
        check_faults(self.faults, n)
        self.emergency_stop = emergency_stop
        self.auth = Authentication(n, required=auth)
        self._forged = tuple(f for f in self.faults if f.forges)
        self._braking: list[BrakingGap] = [
            for_vehicle(
                p.decel_max_mps2, p.actuation_delay_s, p.speed_lag_s, p.length_m, gap_margin_m, dt
            )
            for p in self.presets
        ]
        """Each vehicle's braking-aware gap rule (the leader's: a member in its path)."""
        # The vehicles as they drive (``plant_presets``: fitted to a vehicle run) may differ
        # from the presets the members, the safety rules and the scenario know (the ones
        # the vehicles were deployed with): calibration (docs/calibration.md).
        if plant_presets is not None and len(plant_presets) != n:
            raise ConfigError(
                f"plant_presets: {len(plant_presets)} given for a convoy of {n} vehicles"
            )
        self.plant = BicyclePlant(plant_presets or self.presets, dt)
        # What each vehicle's autopilot believes its heading is, less the truth (rad): the
        # members see and steer by the believed heading, the vehicles move by the true one.
        self.heading_bias = [p.heading_bias_rad for p in (plant_presets or self.presets)]
        self.channel: Channel[VehicleState] = Channel(n, loss, advance_state)
        self.ranging_sensors = [
            (i, p.ranging) for i, p in enumerate(self.presets) if i > 0 and p.ranging
        ]
        self.bounds = [member_tick.ActionBounds.float32(p.max_speed_mps) for p in self.presets]
        """The action space of each vehicle (the leader's unused), as ``core.tick`` clips."""
        self.t = 0.0
        self.step_count = 0
        self.loss = loss
        self.plans: PlanExchange | None = None
        """Plans beside the states (``envs.plans``), once ``enable_plans`` is called."""
        self._clear()

    def enable_plans(self) -> None:
        """Carry plans beside the states from the next ``reset`` on (MPC policies)."""
        if self.plans is None:
            self.plans = PlanExchange(self.members, self.loss)

    # --- the tick ----------------------------------------------------------------------

    def reset(self, seed_seq: np.random.SeedSequence) -> None:
        """Start an episode: scenario, channel, plant and members reset, sensed at t = 0."""
        ss_channel, ss_gps, ss_ranging, ss_scenario = seed_seq.spawn(4)
        self._gps_states = vehicle_states(gps_key(np.random.default_rng(ss_gps)), self.n_vehicles)
        self._ranging_rng = np.random.default_rng(ss_ranging)  # a traffic world's draws
        self._ranging_states = vehicle_states(ranging_key(ss_ranging), self.n_vehicles)
        self.scenario.reset(np.random.default_rng(ss_scenario))
        self.channel.reset(np.random.default_rng(ss_channel))
        self.auth.reset()
        init = self.scenario.initial_state()
        self.plant.reset(init.x, init.y, init.heading, init.speed)
        for m in self.members:
            m.reset()
        if self.plans is not None:
            self.plans.reset(np.random.default_rng(seed_seq.spawn(1)[0]))
        self.t = 0.0
        self.step_count = 0
        self._clear()
        with _collection_paused():
            self.sense()
        self.measure()

    def decide(self, actions: Sequence[np.ndarray]) -> None:
        """The commands of this tick: ``actions[i - 1]`` is follower i's (SI units)."""
        t = self.t
        cmd_v, cmd_dh, modes = self.cmd_speed, self.cmd_heading_change, self.modes
        ranging = self.ranging_readings()
        for i in range(1, self.n_vehicles):
            reading = ranging.get(i) if ranging else None
            d = member_tick.decide(
                self.members[i], self.frames[i], actions[i - 1], self.bounds[i], reading
            )
            cmd_v[i], cmd_dh[i], modes[i] = d.speed_mps, d.heading_change_rad, d.mode
            if d.policy_error:
                self._policy_error(i, t, d.policy_error)
            rule = self._emergency(i, t, reading) if self.emergency_stop else CLEAR
            if self._failed[i] or rule == TOO_CLOSE:
                cmd_v[i] = cmd_dh[i] = 0.0
                modes[i] = "failsafe"
            elif rule == BLIND:  # the predecessor unheard: brake until it is (not latched)
                cmd_v[i] = cmd_dh[i] = 0.0
                modes[i] = "stop"
        tr = self.truth
        h_lead = tr.heading[0] + self.heading_bias[0]
        v0, h0 = self.scenario.leader_command(t, tr.x[0], tr.y[0], h_lead, tr.speed[0])
        cmd_v[0] = v0
        cmd_dh[0] = (h0 - h_lead + math.pi) % (2 * math.pi) - math.pi
        if self.emergency_stop and self._lead_emergency(t):
            cmd_v[0] = cmd_dh[0] = 0.0
            modes[0] = "failsafe"
        if self.faults:
            self._apply_faults(t)

    def advance(self) -> None:
        """Record this tick, step the plant with the decided commands, sense and measure."""
        self.record = self._record(list(self.cmd_speed), list(self.cmd_heading_change))
        h = self.truth.heading
        self.plant.step(self.cmd_speed, [a + b for a, b in zip(h, self.cmd_heading_change)])
        self.step_count += 1
        self.t = self.step_count * self.dt
        self.sense()
        self.measure()

    def sense(self) -> None:
        """Own states -> Tx -> channel -> (forgeries) -> Rx -> frames, at ``self.t``."""
        self.before_sense()
        p, t = self.plant, self.t
        self.truth = tr = Truth.of(p)
        xs, ys = tr.x, tr.y
        if self.gps_noise_m > 0.0:
            dx, dy = gps_noise(self._gps_states, self.gps_noise_m, self.step_count)
            xs = [float(x) + d for x, d in zip(p.x, dx)]
            ys = [float(y) + d for y, d in zip(p.y, dy)]
        for i, m in enumerate(self.members):
            st = VehicleState(
                i,
                t,
                xs[i],
                ys[i],
                tr.speed[i],
                tr.heading[i] + self.heading_bias[i],
                tr.accel[i],
                tr.yaw_rate[i],
                self.lengths[i],
                self.widths[i],
            )
            muted = bool(self._muted) and i in self._muted and self._fault_active(i, t, mutes=True)
            sent = member_tick.begin(m, st, t, may_send=not muted)
            if sent is not None:
                self.channel.send(i, sent, t)
                if self.plans is not None:
                    self.plans.send(
                        i, t, self.modes[i], tr.speed[i], self.presets[i].decel_max_mps2
                    )
        inboxes: list[list[VehicleState]] = [[] for _ in self.members]
        for r, _, msg in self.channel.deliver(t):
            inboxes[r].append(msg)
        if self.plans is not None:
            self.plans.deliver(t)
        if self._forged:
            self._forge(t, inboxes)
        self.frames = [member_tick.sense(m, box, t) for m, box in zip(self.members, inboxes)]

    def measure(self) -> None:
        """Ground-truth gaps, desired gaps, collisions and message counters at ``self.t``."""
        x, y = self.truth.x, self.truth.y
        self.gaps = [math.hypot(x[i - 1] - x[i], y[i - 1] - y[i]) for i in range(1, len(x))]
        self.desired = [f.desired_gap_m for f in self.frames[1:]]
        self.collided = [g < h for g, h in zip(self.gaps, self._half_sum)]
        self.rx = self.channel.delivered_to
        self.lost = self.channel.lost_to

    # --- hooks for a world with more in it (traffic) -------------------------------------

    def before_sense(self) -> None:
        """Called at the start of every ``sense`` (the plant has moved to ``self.t``)."""

    def terminated(self) -> bool:
        """Does the episode end at this tick (a collision)?"""
        return any(self.collided)

    def extra_columns(self) -> dict[str, list[Any]]:
        """Log columns beyond DESIGN.md's for this tick, per vehicle."""
        return {}

    def ranging_readings(self) -> dict[int, Ranging]:
        """Range (m) and range rate (m/s) to the vehicle ahead for vehicles with a sensor,
        in range, with its noise (``envs.ranging_noise``: keyed by episode, vehicle, tick)."""
        out: dict[int, Ranging] = {}
        p = self.plant
        for i, sensor in self.ranging_sensors:
            rng_m, rate = range_and_rate(
                p.x[i],
                p.y[i],
                p.speed[i],
                p.heading[i],
                p.x[i - 1],
                p.y[i - 1],
                p.speed[i - 1],
                p.heading[i - 1],
            )
            if rng_m > sensor.max_range_m or rng_m <= 0.0:
                continue
            n1, n2 = ranging_normals(self._ranging_states[i], self.step_count)
            out[i] = (rng_m + sensor.range_noise_m * n1, rate + sensor.range_rate_noise_mps * n2)
        return out

    # --- records ------------------------------------------------------------------------

    def final_record(self) -> TickRecord:
        """The state the episode ended in, with empty commands."""
        nan = [math.nan] * self.n_vehicles
        return self._record(nan, list(nan))

    def snapshot(self, record: TickRecord) -> TickSnapshot:
        """``record`` as the log reports it (lat/lon from the scenario's origin)."""
        return record_snapshot(record, self.scenario.origin)

    @property
    def policy_errors(self) -> list[int]:
        """Actions refused so far, per vehicle."""
        return list(self._policy_errors)

    # --- internals ----------------------------------------------------------------------

    def _record(self, cmd_v: list[float], cmd_dh: list[float]) -> TickRecord:
        return TickRecord(
            round(self.t, 9),
            self.truth,
            cmd_v,
            cmd_dh,
            list(self.modes),
            [math.nan, *self.gaps],
            list(self.frames),
            [m.msgs_sent for m in self.members],
            [int(v) for v in self.rx],
            [int(v) for v in self.lost],
            self.extra_columns(),
        )

    def _clear(self) -> None:
        n = self.n_vehicles
        self.cmd_speed = [0.0] * n
        self.cmd_heading_change = [0.0] * n
        self.modes = ["coop"] * n
        self.record = None
        self.gaps = [0.0] * (n - 1)
        self.desired = [0.0] * (n - 1)
        self.collided = [False] * (n - 1)
        self.rx = [0] * n
        self.lost = [0] * n
        self.frames = []
        self._estopped = [False] * n
        self._failed = [False] * n  # a refused action stopped it for the episode
        self._policy_errors = [0] * n
        self._faults_seen: set[Fault] = set()
        self._muted: set[int] = {f.vehicle for f in self.faults if f.mutes}
        self.safety_events = []

    def _forge(self, t: float, inboxes: list[list[VehicleState]]) -> None:
        """The forgers' broadcasts this tick: one forged state per active ``forge`` fault,
        offered to every other member (verified when ``security.auth``)."""
        active = [f.vehicle for f in self._forged if f.active(t)]
        claimed = forged_states(active, t, self.truth, self.lengths, self.widths)
        self.auth.deliver_forgeries(claimed, inboxes)

    def _fault_active(self, i: int, t: float, mutes: bool = False, brakes: bool = False) -> bool:
        return any(
            f.vehicle == i and f.active(t) and ((mutes and f.mutes) or (brakes and f.brakes))
            for f in self.faults
        )

    def _apply_faults(self, t: float) -> None:
        """Faulty vehicles brake to rest at their limit (speed setpoint 0, heading held)."""
        for f in self.faults:
            if not f.active(t):
                continue
            if f not in self._faults_seen:
                self._faults_seen.add(f)
                self.safety_events.append((t, f.vehicle, f"fault {f}"))
            if f.brakes:
                self.cmd_speed[f.vehicle] = 0.0
                self.cmd_heading_change[f.vehicle] = 0.0
                self.modes[f.vehicle] = "stop"

    def _policy_error(self, i: int, t: float, why: str) -> None:
        """A refused action: counted; the follower stops for the rest of the episode (the
        vehicle's policy-error failsafe)."""
        self._policy_errors[i] += 1
        if not self._failed[i]:
            self._failed[i] = True
            self.safety_events.append((t, i, f"policy error: {why}"))

    def _emergency(self, i: int, t: float, reading: Ranging | None) -> int:
        """The braking-aware gap rule for follower ``i`` (``core.safety.verdict``; the
        emergency stop latched once it fires). Not consulted for a failed follower."""
        if self._failed[i]:
            return CLEAR
        if self._estopped[i]:
            return TOO_CLOSE
        member = self.members[i]
        if reading is not None:
            gap, closing = reading[0], -reading[1]
        else:
            est = member.gap_estimate(t)
            if est is None:  # never heard: nothing bounds where it is
                return verdict(False, math.nan, 0.0, 0.0, 0.0, 0.0, self._braking[i].numbers)
            gap, closing = est
        return TOO_CLOSE if self._rule_fires(i, i - 1, t, gap, closing) else CLEAR

    def _lead_emergency(self, t: float) -> bool:
        """The leader's braking-aware gap rule to a member in its path (a closed track:
        the convoy's tail), latched once it fires (issue 22, D49)."""
        if self._estopped[0]:
            return True
        ahead = self.members[0].path_gap(t)
        if ahead is None:
            return False
        gap, closing, j = ahead
        return self._rule_fires(0, j, t, gap, closing)

    def _rule_fires(self, i: int, j: int, t: float, gap: float, closing: float) -> bool:
        """Vehicle ``i``'s rule on the centre gap (m) and closing speed (m/s) to vehicle
        ``j`` ahead, which may brake at its limit from now; latches and records a stop."""
        member = self.members[i]
        assert member.own is not None
        rule = self._braking[i]
        ego, decel, accel = member.own.speed, member.decel_of(j), member.own.accel
        bumper = bumper_gap(gap, self.lengths[i], self.lengths[j])
        if not rule.too_close(bumper, closing, ego, decel, accel):
            return False
        self._estopped[i] = True
        why = rule.reason(bumper, closing, ego, decel, accel)
        self.safety_events.append((t, i, "emergency stop: " + why))
        return True


def record_snapshot(record: TickRecord, origin: Origin) -> TickSnapshot:
    """``record`` as the log reports it, lat/lon from the convoy ``origin``."""
    tr = record.truth
    lat, lon, _ = (np.asarray(v) for v in enu_to_geodetic(origin, np.array(tr.x), np.array(tr.y)))
    f = record.frames
    return TickSnapshot(
        t_s=record.t,
        x_m=tr.x,
        y_m=tr.y,
        lat_deg=lat.tolist(),
        lon_deg=lon.tolist(),
        speed_mps=tr.speed,
        heading_rad=tr.heading,
        accel_mps2=tr.accel,
        cmd_speed_mps=record.cmd_speed,
        cmd_heading_change_rad=record.cmd_heading_change,
        mode=record.modes,
        gap_m=record.gaps,
        desired_gap_m=[x.desired_gap_m for x in f],
        spacing_error_m=[x.spacing_error_m for x in f],
        msgs_sent=record.msgs_sent,
        msgs_received=record.msgs_received,
        msgs_lost=record.msgs_lost,
        pred_msg_age_s=[x.pred_msg_age_s for x in f],
        extra=record.extra,
    )


def forged_states(
    vehicles: Sequence[int],
    t: float,
    truth: Truth,
    lengths: Sequence[float],
    widths: Sequence[float],
) -> list[VehicleState]:
    """What a forger in the name of each of ``vehicles`` claims at ``t`` (s): its true
    position, speed and heading, no acceleration or yaw rate."""
    return [
        VehicleState(
            v,
            t,
            truth.x[v],
            truth.y[v],
            truth.speed[v],
            truth.heading[v],
            0.0,
            0.0,
            lengths[v],
            widths[v],
        )
        for v in vehicles
    ]
