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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from openconvoy.core import ladder as ladder_mod
from openconvoy.core.buffer import StateBuffer
from openconvoy.core.config import Range
from openconvoy.core.estimate import TargetEstimate, dead_reckon, gap_and_closing
from openconvoy.core.gates import RxGate, TriggerConfig, TxGate, is_plugin_topology
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.observation import (
    DERIVED_FEATURES,
    LOOKAHEAD_S,
    STATE_FEATURES,
    ObservationLayout,
    ego_state,
    to_ego,
)
from openconvoy.core.policy import make_action
from openconvoy.core.spacing import GapChain, SpacingConfig, SpacingPolicy
from openconvoy.core.state import VehicleState, wrap_angle
from openconvoy.core.trail import Projection, Trail

_NF = len(STATE_FEATURES)
_ND = len(DERIVED_FEATURES)
PATH_CONE = 0.5
"""Half-width growth (m per m ahead) of the corridor in which the leader looks for a
member in its path (``ConvoyMember.path_gap``)."""


@dataclass(frozen=True)
class MemberConfig:
    """The member side of an implementation: ρ (``topology``), τ (``trigger``), σ's
    desired gaps (``spacing``), the staleness ``ladder``, and the observation's ``M``, ``k``.
    ``topology``, ``trigger.kind`` and ``spacing.kind`` may name plug-ins
    (``core.plugins``); ``topology_params`` are a plug-in topology's keyword arguments."""

    topology: str = "all-predecessors"
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    spacing: SpacingConfig = field(default_factory=SpacingConfig)
    ladder: LadderConfig = field(default_factory=LadderConfig)
    M: Annotated[int, Range(1, 100)] = 2
    k: Annotated[int, Range(1, 100)] = 3
    trail_spacing_m: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 0.2
    topology_params: dict[str, Any] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        RxGate(self.topology, 1, 2, self.topology_params)  # validates the topology name

    @property
    def plugins(self) -> list[str]:
        """The plug-in components of the member side, as ``"spacing module:Name"``."""
        out = [f"topology {self.topology}"] if is_plugin_topology(self.topology) else []
        if self.trigger.is_plugin:
            out.append(f"trigger {self.trigger.kind}")
        if self.spacing.is_plugin:
            out.append(f"spacing {self.spacing.kind}")
        return out

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

    @property
    def rule_fresh_age_s(self) -> float:
        """Message age (s) up to which the braking rule takes the vehicle ahead at its
        constant speed before braking at its limit: 0, whatever the trigger. It may have
        braked since it sent; an event trigger's silence does not say otherwise, since a
        dead sender is silent too (issue 22's fault matrix: with the event trigger's 1.1 s,
        ``dead:1@3`` on ``emergency-braking`` at PER 0.3 collided)."""
        return 0.0


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
        self.rx = RxGate(config.topology, vehicle_id, n_vehicles, config.topology_params)
        self.tx = TxGate(config.trigger)
        self.spacing = SpacingPolicy(config.spacing)
        self.buffer = StateBuffer(config.k, config.trail_spacing_m)
        # What the gates, the layout and σ say is fixed for the member's life; computed
        # once, because every tick reads it for every message and target.
        # ρ decides what the policy sees; the braking rule sees more: every member keeps
        # its immediate predecessor's messages, the leader everyone's (a convoy vehicle
        # in its path on a closed track), whatever ρ says (issue 22, D47, D49).
        self._control = self.rx.kept_row().tolist()  # ρ(i, j) for every j, in bulk
        self._keeps = [
            self._control[j] or j == vehicle_id - 1 or (vehicle_id == 0 and j != 0)
            for j in range(n_vehicles)
        ]
        self._needed = tuple(self.rx.needed())
        self._gaps = GapChain(self.spacing, self.lengths)
        self._fresh_age_s = config.fresh_age_s
        self._rule_fresh_s = config.rule_fresh_age_s
        self._stop_after_s = config.ladder.stop_after_s
        lay = self.layout
        self._slots = [
            (lay.slot_offset(slot), vid)
            for slot, vid in zip(lay.slots, self._slot_ids())
            if vid is not None and self._control[vid]
        ]
        targets = self._slot_ids()[: len(lay.targets)]
        preds_in_slots = set(targets[1:])
        self._targets = [
            (name, vid, lay.target_offset(name))
            for name, vid in zip(lay.targets, targets)
            if vid is not None
            and self._control[vid]
            and not (name == "leader" and vid in preds_in_slots)
        ]
        """(target name, vehicle id, offset) of every target slot with a vehicle in it."""
        self._nearest_first = (*lay.targets[1:], "leader")
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
        # The last estimate of each target with the message and time it was made for:
        # the frame and the safety rule ask for the same one within a tick.
        self._estimates: dict[int, tuple[VehicleState, float, TargetEstimate | None]] = {}

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
        """ρ: keep ``msg`` in R^i if the topology wants its sender, or the braking rule
        does (the predecessor; for the leader, everyone). Returns True if kept."""
        j = msg.vehicle_id
        keeps = self._keeps
        if not (keeps[j] if 0 <= j < len(keeps) else self.rx.keeps(j)):
            self.msgs_filtered += 1
            return False
        self.buffer.push(msg)
        self.msgs_received += 1
        return True

    def receive_all(self, inbox: Iterable[VehicleState], now: float) -> None:
        """``receive`` for every message of ``inbox``, in order."""
        keeps, n = self._keeps, len(self._keeps)
        push = self.buffer.push
        kept = filtered = 0
        for msg in inbox:
            j = msg.vehicle_id
            if keeps[j] if 0 <= j < n else self.rx.keeps(j):
                push(msg)
                kept += 1
            else:
                filtered += 1
        self.msgs_received += kept
        self.msgs_filtered += filtered

    def observation(self, now: float) -> np.ndarray:
        """The observation array at ``now`` (``sense(now).observation``)."""
        return self.sense(now).observation

    def sense(self, now: float) -> Frame:
        """The observation array at ``now`` (layout in ``openconvoy.core.observation``)
        and the derived values, in one ``Frame``; leaves nothing behind that ``supervise``
        reads (it takes the frame)."""
        if self.own is None:
            raise RuntimeError("observe_own() must be called before sense()")
        # Built as Python floats and made a float32 array once (the same rounding as
        # writing each value into the array; far fewer numpy calls).
        obs = [0.0] * self.layout.size
        ego = self.own
        c, s = math.cos(ego.heading), math.sin(ego.heading)
        ex, ey, eh = ego.x, ego.y, ego.heading
        states, seen = self.buffer.states, ego_state  # (a local: called per state)
        for base, vid in self._slots:
            history = states(vid)
            if not history:
                continue
            vals: list[float] = []
            for st in history:
                x, y, dh, age = seen(c, s, st.x - ex, st.y - ey, st.heading - eh, now - st.t)
                vals += (x, y, dh, st.speed, st.accel, age, 1.0)
            obs[base : base + len(vals)] = vals
        o = self.layout.own_offset
        obs[o : o + 3] = (ego.speed, ego.accel, ego.yaw_rate)
        return self._fill_targets(obs, now)

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
        ladder = self.config.ladder
        # (``rung`` is COOP whatever the age with the ladder off: no age to compute then.)
        mode = (
            ladder_mod.rung(self.needed_age(frame.t), ladder) if ladder.enabled else ladder_mod.COOP
        )
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
        if not self._needed:
            return 0.0
        oldest = self.buffer.oldest_newest_t(self._needed)
        return math.inf if oldest is None else max(0.0, now - oldest)

    def estimate(self, vehicle_id: int, now: float) -> TargetEstimate | None:
        """Where ``vehicle_id`` is at ``now`` by its newest message (see the class doc);
        None when unheard or older than the ladder's stop age."""
        latest = self.buffer.latest(vehicle_id)
        if latest is None:
            return None
        cached = self._estimates.get(vehicle_id)
        if cached is not None and cached[0] is latest and cached[1] == now:
            return cached[2]
        est = dead_reckon(
            latest, now, self._fresh_age_s, self._stop_after_s, self._decel(vehicle_id)
        )
        self._estimates[vehicle_id] = (latest, now, est)
        return est

    def gap_estimate(self, now: float) -> tuple[float, float] | None:
        """``(gap_m, closing_mps)`` to the immediate predecessor from its messages: centre
        to centre, and how fast it shrinks (positive = closing); None when never heard.

        Unlike a target, this estimate does not expire at the ladder's stop age: a
        predecessor silent for longer got no further than braking at its limit takes it
        (and a stopped car stays put), so the braking rule, which reads it, keeps seeing
        it there. Expiring it let a policy drive into a dead predecessor unchecked.

        The predecessor is taken as braking at its limit since its newest message, however
        fresh (``MemberConfig.rule_fresh_age_s``): it may have started when it sent, and
        where it stops does not depend on the message's age then. Dead-reckoned at its
        speed, a lossy link let the rule fire late (issue 22's fault matrix)."""
        i = self.vehicle_id
        if i == 0 or self.own is None:
            return None
        latest = self.buffer.latest(i - 1)
        if latest is None:
            return None
        est = dead_reckon(latest, now, self._rule_fresh_s, math.inf, self._decel(i - 1))
        assert est is not None
        return gap_and_closing(self.own, est)

    def path_gap(self, now: float) -> tuple[float, float, int] | None:
        """The leader's gap source: ``(gap_m, closing_mps, vehicle)`` to the nearest
        convoy member in its path by that member's messages (centre to centre; positive
        closing = closing), None when none is. In its path: ahead of the leader
        (``along`` > 0) and within half the two lengths plus ``PATH_CONE`` of the
        distance ahead of its heading line (a cone: a track's curve, or a follower
        stopped off the line, comes into it before the leader gets there). Estimates as
        ``gap_estimate``'s: braking since the message."""
        own = self.own
        if self.vehicle_id != 0 or own is None:
            return None
        c, s = math.cos(own.heading), math.sin(own.heading)
        best: tuple[float, float, int] | None = None
        for j in range(1, self.n_vehicles):
            latest = self.buffer.latest(j)
            if latest is None:
                continue
            est = dead_reckon(latest, now, self._rule_fresh_s, math.inf, self._decel(j))
            assert est is not None
            dx, dy = est.x - own.x, est.y - own.y
            half = 0.5 * (self._length(0) + self._length(j))
            along = c * dx + s * dy
            if not (along > 0.0 and abs(c * dy - s * dx) < half + PATH_CONE * along):
                continue
            gap, closing = gap_and_closing(own, est)
            if best is None or gap < best[0]:
                best = (gap, closing, j)
        return best

    def decel_of(self, vid: int) -> float:
        """Vehicle ``vid``'s braking limit (m/s²; inf when unknown)."""
        return self._decel(vid)

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

    def _fill_targets(self, obs: list[float], now: float) -> Frame:
        """Derived and path features into ``obs``; the frame with the observation (as
        float32) and the logged desired gap, spacing error and message age."""
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
        found: dict[str, tuple[Trail, tuple[float, float], float, float, Projection, int]] = {}
        for name, vid, o in self._targets:
            est = self.estimate(vid, now)
            if est is None:  # unheard, or too old to say where it is
                continue
            desired = self._gaps.gap_to(i, vid, ego.speed)
            trail = self.buffer.trail(vid)
            assert trail is not None
            head = (est.x, est.y)
            projection = trail.project(
                head, est.heading, ego.x, ego.y, desired, self._last_s.get(vid)
            )
            self._last_s[vid] = projection.s
            arc = projection.arc_to_head
            obs[o : o + _ND] = (arc, desired, arc - desired, est.speed, 1.0)
            found[name] = (trail, head, est.heading, est.speed - ego.speed, projection, o)
        # The nearest heard predecessor gives the path to steer on and the logged error.
        for name in self._nearest_first:
            if name in found:
                trail, head, heading, closing, projection, o = found[name]
                spacing_error = float(np.float32(obs[o + 2]))  # as the observation holds it
                if name == "pred_1":
                    pred_gap = (projection.arc_to_head, closing)
                fill_path(obs, self.layout.path_offset, ego, trail, head, heading, projection)
                break
        observation = np.array(obs, dtype=np.float32)
        return Frame(now, observation, desired_gap, spacing_error, pred_age, pred_gap)


def fill_path(
    obs: list[float],
    o: int,
    ego: VehicleState,
    trail: Trail,
    head: tuple[float, float],
    heading: float,
    projection: Projection,
) -> None:
    """The path features (``PATH_FEATURES``, at offset ``o`` of ``obs``) of the trail the
    ego steers on: its offset and heading error there and the lookahead points."""
    c, s = math.cos(ego.heading), math.sin(ego.heading)
    # The projection gives the ego's offset from the path; the path's offset from the
    # ego (what a steering law corrects) is its negative.
    obs[o] = -projection.cross_track
    obs[o + 1] = wrap_angle(projection.heading - ego.heading)
    scale = max(1.0, abs(ego.speed))
    s_head = trail.head_s(head)
    for j, t in enumerate(LOOKAHEAD_S):
        px, py = trail.point_at(head, heading, projection.s + t * scale, s_head)
        obs[o + 2 + 2 * j], obs[o + 3 + 2 * j] = to_ego(c, s, px - ego.x, py - ego.y)
    obs[o + 8] = 1.0
