"""The convoy member: R^i + ρ + τ + the staleness ladder + the observation builder.

The unit that makes sim2real "unchanged" (DESIGN.md, One member, two worlds): the
simulator and the vehicle bridge drive the same object through the same calls each tick,
written once in ``core.tick``::

    member.observe_own(own_state)
    if member.wants_to_send(now): broadcast(own_state)
    for msg in inbox: member.receive(msg, now)
    frame = member.sense(now)               # observation + the derived values, explicit
    action, mode = member.supervise(policy.act(frame.observation), frame, ranging)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from openconvoy.core import ladder as ladder_mod
from openconvoy.core.buffer import StateBuffer
from openconvoy.core.config import Range
from openconvoy.core.gates import RxGate, TriggerConfig, TxGate
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.observation import (
    DERIVED_FEATURES,
    LOOKAHEAD_S,
    MAX_AGE_S,
    STATE_FEATURES,
    ObservationLayout,
)
from openconvoy.core.policy import make_action
from openconvoy.core.spacing import SpacingConfig, SpacingPolicy
from openconvoy.core.state import VehicleState, wrap_angle
from openconvoy.core.trail import Projection, Trail

_NF = len(STATE_FEATURES)
_ND = len(DERIVED_FEATURES)


@dataclass(frozen=True)
class MemberConfig:
    """The member side of an implementation: ρ (``topology``), τ (``trigger``), σ's
    desired gaps (``spacing``), the staleness ``ladder``, and the observation's ``M``, ``k``."""

    topology: str = "all-predecessors"
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    spacing: SpacingConfig = field(default_factory=SpacingConfig)
    ladder: LadderConfig = field(default_factory=LadderConfig)
    M: Annotated[int, Range(1, 100)] = 2
    k: Annotated[int, Range(1, 100)] = 3
    trail_spacing_m: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 0.2

    def __post_init__(self) -> None:
        RxGate(self.topology, 1, 2)  # validates the topology name

    @property
    def layout(self) -> ObservationLayout:
        return ObservationLayout(M=self.M, k=self.k)

    @property
    def fresh_age_s(self) -> float:
        """Message age (s) up to which a target is fresh: dead-reckoned at constant speed
        and trusted. The ladder's ``degrade_after_s``, or longer for an event trigger,
        whose senders stay silent up to ``max_silence_s`` exactly while the others'
        constant-speed extrapolation of them holds."""
        t = self.trigger
        silence = t.max_silence_s + t.period_s if t.kind == "event" else 0.0
        return max(self.ladder.degrade_after_s, silence)


def member_config_for(config: MemberConfig | None, spacing: SpacingConfig) -> MemberConfig:
    """The member config a world runs: the policy's, or for a policy without one the
    scenario's ``spacing`` and the defaults otherwise (the same rule in every world)."""
    return config if config is not None else MemberConfig(spacing=spacing)


@dataclass(frozen=True, slots=True)
class Frame:
    """What the member sensed at ``t`` (s): the policy's ``observation`` and the derived
    values the log reports and ``supervise`` uses. ``desired_gap_m`` (centre to centre,
    from σ at the own speed), ``spacing_error_m`` (path-based, to the nearest heard
    predecessor) and ``pred_msg_age_s`` are NaN where they do not exist (the leader; no
    message heard); ``pred_gap`` is ``(arc gap m, closing m/s)`` to the immediate
    predecessor by its messages, or None."""

    t: float
    observation: np.ndarray
    desired_gap_m: float = math.nan
    spacing_error_m: float = math.nan
    pred_msg_age_s: float = math.nan
    pred_gap: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class TargetEstimate:
    """Where a heard vehicle is now by its newest message: ENU position (m), speed (m/s),
    heading (rad), message age (s), and ``stale`` (older than ``MemberConfig.fresh_age_s``)."""

    x: float
    y: float
    speed: float
    heading: float
    age: float
    stale: bool


class ConvoyMember:
    """One vehicle's cooperative state and gates. ``lengths[i]`` is vehicle i's length (m);
    ``decels[i]`` its braking limit (m/s²), used to bound where a silent vehicle can be
    (None: a silent vehicle is taken to have stopped where it was last heard).

    Target ages (issue 10): a message no older than ``MemberConfig.fresh_age_s`` (the
    ladder's ``degrade_after_s``, longer for event triggers) is dead-reckoned at constant
    speed; an older one as if its sender had braked at its limit
    from the moment it was sent (it may have: only slowing is safe to assume); older than
    ``stop_after_s`` it is no target at all. These ages apply with the ladder off too.
    """

    def __init__(
        self,
        vehicle_id: int,
        n_vehicles: int,
        config: MemberConfig,
        lengths: Sequence[float] | None = None,
        decels: Sequence[float] | None = None,
    ) -> None:
        self.vehicle_id = vehicle_id
        self.n_vehicles = n_vehicles
        self.config = config
        self.layout = config.layout
        self.lengths = list(lengths) if lengths is not None else [0.0] * n_vehicles
        self.decels = list(decels) if decels is not None else [math.inf] * n_vehicles
        self.rx = RxGate(config.topology, vehicle_id, n_vehicles)
        self.tx = TxGate(config.trigger)
        self.spacing = SpacingPolicy(config.spacing)
        self.buffer = StateBuffer(config.k, config.trail_spacing_m)
        self.reset()

    def reset(self) -> None:
        """Forget everything heard; counters to zero."""
        self.buffer.clear()
        self.tx.reset()
        self.own: VehicleState | None = None
        self.msgs_sent = 0
        self.msgs_received = 0
        self.msgs_filtered = 0
        self.mode = ladder_mod.COOP  # the last mode ``supervise`` decided
        self._last_s: dict[int, float] = {}  # last projection on each trail: a warm start

    # --- the tick --------------------------------------------------------------------

    def observe_own(self, state: VehicleState) -> None:
        """Take the own state (from the plant or the autopilot's telemetry)."""
        self.own = state

    def wants_to_send(self, now: float) -> bool:
        """τ: True when the own state should be broadcast now (counted as sent)."""
        if self.own is None:
            return False
        send = self.tx.should_send(self.own, now)
        self.msgs_sent += send
        return send

    def receive(self, msg: VehicleState, now: float) -> bool:
        """ρ: keep ``msg`` in R^i if the topology wants its sender. Returns True if kept."""
        if msg.vehicle_id == self.vehicle_id or not self.rx.keeps(msg.vehicle_id):
            self.msgs_filtered += 1
            return False
        self.buffer.push(msg)
        self.msgs_received += 1
        return True

    def observation(self, now: float) -> np.ndarray:
        """The observation array at ``now`` (``sense(now).observation``)."""
        return self.sense(now).observation

    def sense(self, now: float) -> Frame:
        """The observation array at ``now`` (layout in ``openconvoy.core.observation``)
        and the derived values, in one ``Frame``; leaves nothing behind that ``supervise``
        reads (it takes the frame)."""
        if self.own is None:
            raise RuntimeError("observe_own() must be called before sense()")
        lay = self.layout
        obs = lay.zeros()
        ego = self.own
        c, s = math.cos(ego.heading), math.sin(ego.heading)
        slot_ids = self._slot_ids()
        for slot, vid in zip(lay.slots, slot_ids):
            if vid is None:
                continue
            vals: list[float] = []
            for st in self.buffer.history(vid):
                dx, dy = st.x - ego.x, st.y - ego.y
                age = now - st.t
                vals += (
                    c * dx + s * dy,
                    -s * dx + c * dy,
                    wrap_angle(st.heading - ego.heading),
                    st.speed,
                    st.accel,
                    MAX_AGE_S if age > MAX_AGE_S else (age if age > 0.0 else 0.0),
                    1.0,
                )
            base = lay.slot_offset(slot)
            obs[base : base + len(vals)] = vals
        o = lay.own_offset
        obs[o : o + 3] = (ego.speed, ego.accel, ego.yaw_rate)
        return self._fill_targets(obs, slot_ids, now)

    def supervise(
        self,
        action: np.ndarray,
        frame: Frame,
        ranging: tuple[float, float] | None = None,
    ) -> tuple[np.ndarray, str]:
        """Apply the staleness ladder to the policy's action, at the time of ``frame``
        (what ``sense`` returned this tick).

        ``ranging`` is ``(range_m, range_rate_mps)`` to the vehicle ahead, centre to
        centre, from a ranging sensor when the vehicle has one. Returns the action to
        apply and the mode (``coop``, ``degraded``, ``stop``).
        """
        mode = ladder_mod.rung(self.needed_age(frame.t), self.config.ladder)
        if mode == ladder_mod.COOP and self._ranging_override(ranging, frame):
            mode = ladder_mod.DEGRADED
        self.mode = mode
        if self.mode == ladder_mod.COOP:
            return np.asarray(action, dtype=np.float32), self.mode
        if self.mode == ladder_mod.DEGRADED:
            estimate = ranging if ranging is not None else frame.pred_gap
            if estimate is not None and self.own is not None:
                desired = self.spacing.pair_gap(
                    self.own.speed, self._length(self.vehicle_id), self._length(self.vehicle_id - 1)
                )
                v = ladder_mod.acc_speed(
                    estimate[0], estimate[1], self.own.speed, desired, self.config.ladder
                )
                return make_action(min(float(action[0]), v), float(action[1])), self.mode
            self.mode = ladder_mod.STOP
        return make_action(0.0, 0.0), self.mode

    def needed_age(self, now: float) -> float:
        """Age (s) of the oldest newest-message among the vehicles the topology needs
        (every kept predecessor; inf if one is unheard; 0 for the leader)."""
        return max((self.buffer.age(v, now) for v in self.rx.needed()), default=0.0)

    def estimate(self, vehicle_id: int, now: float) -> TargetEstimate | None:
        """Where ``vehicle_id`` is at ``now`` by its newest message (see the class doc);
        None when unheard or older than the ladder's stop age."""
        latest = self.buffer.latest(vehicle_id)
        if latest is None:
            return None
        ladder = self.config.ladder
        age = max(now - latest.t, 0.0)
        if age > ladder.stop_after_s:
            return None
        v, h = latest.speed, latest.heading
        if age <= self.config.fresh_age_s:
            d, speed, stale = v * age, v, False
        else:
            a = self._decel(vehicle_id)
            if v <= 0.0 or math.isinf(a):
                d, speed = 0.0, 0.0
            else:
                tau = min(age, v / a)
                d, speed = v * tau - 0.5 * a * tau * tau, max(v - a * age, 0.0)
            stale = True
        return TargetEstimate(
            latest.x + d * math.cos(h), latest.y + d * math.sin(h), speed, h, age, stale
        )

    def gap_estimate(self, now: float) -> tuple[float, float] | None:
        """``(gap_m, closing_mps)`` to the immediate predecessor from its messages: centre
        to centre, and how fast it shrinks (positive = closing); None when unknown."""
        i = self.vehicle_id
        if i == 0 or self.own is None:
            return None
        est = self.estimate(i - 1, now)
        if est is None:
            return None
        own = self.own
        dx, dy = est.x - own.x, est.y - own.y
        gap = math.hypot(dx, dy)
        if gap <= 0.0:
            return 0.0, max(own.speed - est.speed, 0.0)
        # Velocities projected on the line between the two: the range rate, negated.
        vx = own.speed * math.cos(own.heading) - est.speed * math.cos(est.heading)
        vy = own.speed * math.sin(own.heading) - est.speed * math.sin(est.heading)
        return gap, (dx * vx + dy * vy) / gap

    # --- helpers ---------------------------------------------------------------------

    def _decel(self, vid: int) -> float:
        a = self.decels[vid] if 0 <= vid < len(self.decels) else math.inf
        return a if a > 0.0 else math.inf

    def _ranging_override(self, ranging: tuple[float, float] | None, frame: Frame) -> bool:
        """The ranging target is closer than the predecessor heard by V2V (a cut-in) or
        than the desired gap: follow it by ranging (``ladder.ranging_override``)."""
        if ranging is None or frame.pred_gap is None:
            return False
        desired = frame.desired_gap_m if frame.desired_gap_m == frame.desired_gap_m else 0.0
        return ladder_mod.ranging_override(
            ranging[0], frame.pred_gap[0], desired, self.config.ladder
        )

    def _length(self, vid: int) -> float:
        return self.lengths[vid] if 0 <= vid < len(self.lengths) else 0.0

    def _slot_ids(self) -> list[int | None]:
        """Vehicle id in each state slot (None when the slot has no vehicle)."""
        i, n = self.vehicle_id, self.n_vehicles
        preds: list[int | None] = [
            i - m if i - m >= 0 else None for m in range(1, self.layout.M + 1)
        ]
        return [0 if i > 0 else None, *preds, i + 1 if i + 1 < n else None]

    def _fill_targets(self, obs: np.ndarray, slot_ids: list[int | None], now: float) -> Frame:
        """Derived and path features into ``obs``; the frame with the logged desired gap,
        spacing error and message age."""
        lay = self.layout
        ego = self.own
        assert ego is not None
        i = self.vehicle_id
        desired_gap = (
            self.spacing.pair_gap(ego.speed, self._length(i), self._length(i - 1))
            if i > 0
            else math.nan
        )
        pred_age = self.buffer.age(i - 1, now) if i > 0 else math.nan
        if math.isinf(pred_age):
            pred_age = math.nan
        spacing_error = math.nan
        pred_gap: tuple[float, float] | None = None
        targets = slot_ids[: len(lay.targets)]
        preds_in_slots = set(targets[1:])
        found: dict[str, tuple[Trail, tuple[float, float], float, float, Projection]] = {}
        for name, vid in zip(lay.targets, targets):
            if vid is None or (name == "leader" and vid in preds_in_slots):
                continue
            est = self.estimate(vid, now)
            if est is None:  # unheard, or too old to say where it is
                continue
            desired = self.spacing.gap_to(i, vid, ego.speed, self.lengths)
            trail = self.buffer.trail(vid)
            assert trail is not None
            head = (est.x, est.y)
            projection = trail.project(
                head, est.heading, ego.x, ego.y, desired, self._last_s.get(vid)
            )
            self._last_s[vid] = projection.s
            arc = projection.arc_to_head
            o = lay.target_offset(name)
            obs[o : o + _ND] = (arc, desired, arc - desired, est.speed, 1.0)
            found[name] = (trail, head, est.heading, est.speed - ego.speed, projection)
        # The nearest heard predecessor gives the path to steer on and the logged error.
        for name in (*lay.targets[1:], "leader"):
            if name in found:
                trail, head, heading, closing, projection = found[name]
                o = lay.target_offset(name)
                spacing_error = float(obs[o + 2])
                if name == "pred_1":
                    pred_gap = (projection.arc_to_head, closing)
                self._fill_path(obs, trail, head, heading, projection)
                break
        return Frame(now, obs, desired_gap, spacing_error, pred_age, pred_gap)

    def _fill_path(
        self,
        obs: np.ndarray,
        trail: Trail,
        head: tuple[float, float],
        heading: float,
        projection: Projection,
    ) -> None:
        ego = self.own
        assert ego is not None
        c, s = math.cos(ego.heading), math.sin(ego.heading)
        o = self.layout.path_offset
        # The projection gives the ego's offset from the path; the path's offset from the
        # ego (what a steering law corrects) is its negative.
        obs[o] = -projection.cross_track
        obs[o + 1] = wrap_angle(projection.heading - ego.heading)
        scale = max(1.0, abs(ego.speed))
        for j, t in enumerate(LOOKAHEAD_S):
            px, py = trail.point_at(head, heading, projection.s + t * scale)
            dx, dy = px - ego.x, py - ego.y
            obs[o + 2 + 2 * j] = c * dx + s * dy
            obs[o + 3 + 2 * j] = -s * dx + c * dy
        obs[o + 8] = 1.0
