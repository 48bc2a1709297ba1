"""One member's control tick, written once for every world (simulator, traffic, vehicle).

The sequence (DESIGN.md, One member, two worlds) in three steps, because a simulator sends
for every vehicle before any of them receives, and a PettingZoo env hands observations out
and takes actions back between sensing and deciding:

1. ``begin``: the own state in; τ says whether to broadcast it (``may_send`` False
   mutes it: a fault, or a vehicle whose autopilot link is lost);
2. ``sense``: ρ on every message of the inbox, then the observation and the derived
   values (``member.Frame``);
3. ``decide``: the policy's action checked (a non-finite one is a policy error: stop),
   clipped to the action space (``ActionBounds``), then the staleness ladder
   (``member.supervise``, with the ranging sensor's reading when there is one).

``exchange`` runs steps 1 and 2 for members that tick together: every member begins and
broadcasts on a ``Network``, then every member senses what it delivers. The simulator
(``envs.world.ConvoyWorld``) runs its convoy through ``exchange`` and later ``decide``.
``tick`` runs all three with ``policy.act`` in between (a policy that raises is a policy
error too): a world with one member per process (a vehicle) calls it as is, its V2V passed
in as a ``Radio`` and run through ``exchange`` as a network of one (sent to right after τ,
received from right before ρ) and ``started`` asked after sensing, before acting (a
vehicle senses, but does not act, while it waits for its convoy to start). So a change to
a step, or to the order of steps 1 and 2, reaches every world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from openconvoy.core import ladder
from openconvoy.core.member import ConvoyMember, Frame
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD, PolicyFailure
from openconvoy.core.state import VehicleState

Ranging = tuple[float, float]
"""``(range_m, range_rate_mps)`` to the vehicle ahead, centre to centre."""


class Actor(Protocol):
    """What the tick asks of a follower's policy: ``act`` on an observation (a
    ``core.policy.Policy``, or a wrapper returning a ``PolicyFailure`` instead of raising)."""

    def act(self, observation: np.ndarray) -> np.ndarray | PolicyFailure: ...


class Radio(Protocol):
    """One member's V2V, for a world that ticks one member at a time (a vehicle)."""

    def send(self, state: VehicleState, now: float) -> None:
        """Broadcast the own ``state`` at time ``now`` (s): τ said so."""

    def receive(self, now: float) -> list[VehicleState]:
        """The vehicle states heard since the last tick, at time ``now`` (s), in order."""


class Network(Protocol):
    """The V2V of a world that ticks its members together (the simulator): every member
    sends before any receives."""

    def send(self, sender: int, state: VehicleState, now: float) -> None:
        """Member ``sender`` (its index in the world) broadcasts ``state`` at ``now`` (s)."""

    def deliver(self, now: float) -> list[list[VehicleState]]:
        """What each member receives at ``now`` (s), one inbox per member, in order."""


class _Heard:
    """A vehicle's ``Radio`` as the ``Network`` of a world of one member; ``sent`` keeps
    the state it broadcast (None when τ said no)."""

    __slots__ = ("radio", "sent")

    def __init__(self, radio: Radio) -> None:
        self.radio = radio
        self.sent: VehicleState | None = None

    def send(self, sender: int, state: VehicleState, now: float) -> None:
        self.sent = state
        self.radio.send(state, now)

    def deliver(self, now: float) -> list[list[VehicleState]]:
        return [self.radio.receive(now)]


@dataclass(frozen=True, slots=True)
class ActionBounds:
    """The action space: speed setpoint in ``[0, max_speed_mps]`` (m/s), heading change in
    ``±max_heading_change_rad`` (rad)."""

    max_speed_mps: float
    max_heading_change_rad: float = MAX_HEADING_CHANGE_RAD

    @classmethod
    def float32(cls, max_speed_mps: float) -> ActionBounds:
        """Bounds equal to those of a float32 action space (a ``gymnasium`` Box): the
        simulator's space and a vehicle's clip agree to the bit."""
        return cls(float(np.float32(max_speed_mps)), float(np.float32(MAX_HEADING_CHANGE_RAD)))

    def clip(self, speed: float, change: float) -> tuple[float, float]:
        """``(speed, change)`` clipped to the bounds (finite inputs)."""
        hi_v, hi_h = self.max_speed_mps, self.max_heading_change_rad
        speed = 0.0 if speed < 0.0 else (hi_v if speed > hi_v else speed)
        change = -hi_h if change < -hi_h else (hi_h if change > hi_h else change)
        return speed, change


@dataclass(frozen=True, slots=True)
class Decision:
    """What the member decided: the ``action`` to apply (``[speed_mps,
    heading_change_rad]``, float32), its ``mode`` (``coop``, ``degraded``, ``stop``), and
    ``policy_error``: why the policy's action was refused ("" when it was not)."""

    action: np.ndarray
    mode: str
    policy_error: str = ""

    @property
    def speed_mps(self) -> float:
        return float(self.action[0])

    @property
    def heading_change_rad(self) -> float:
        return float(self.action[1])


@dataclass(frozen=True, slots=True)
class TickResult:
    """One tick of one member: ``broadcast`` (the own state sent, or None), the ``frame``
    sensed, whether the member had ``started`` (False: it sensed only, waiting for its
    convoy) and the ``decision`` taken (None for a member without a policy, a leader, or
    one not started)."""

    broadcast: VehicleState | None
    frame: Frame
    decision: Decision | None
    started: bool = True


def non_finite_reason(speed: float, change: float) -> str:
    """Why an action ``[speed, change]`` with a NaN or infinite value is refused."""
    return f"non-finite action {speed}, {change}"


def stop(policy_error: str = "") -> Decision:
    """Speed 0, heading held: the ``stop`` decision."""
    return Decision(np.zeros(2, dtype=np.float32), ladder.STOP, policy_error)


def begin(
    member: ConvoyMember, own: VehicleState, now: float, may_send: bool = True
) -> VehicleState | None:
    """Step 1: the own state in; the state to broadcast now (τ), or None."""
    member.observe_own(own)
    return own if may_send and member.wants_to_send(now) else None


def sense(member: ConvoyMember, inbox: Iterable[VehicleState], now: float) -> Frame:
    """Step 2: ρ on each message received, then the frame at ``now``."""
    member.receive_all(inbox, now)
    return member.sense(now)


def exchange(
    members: Sequence[ConvoyMember],
    owns: Sequence[VehicleState],
    now: float,
    network: Network,
    may_send: Sequence[bool],
) -> list[Frame]:
    """Steps 1 and 2 for members ticking together at ``now`` (s): each ``begin``s with its
    own state and its broadcast goes on the ``network`` (members in order), then every
    member ``sense``s what the network delivers to it. The simulator runs its whole convoy
    through this; ``tick`` runs a vehicle through it as a world of one."""
    for i, (member, own, ok) in enumerate(zip(members, owns, may_send)):
        sent = begin(member, own, now, ok)
        if sent is not None:
            network.send(i, sent, now)
    inboxes = network.deliver(now)
    return [sense(member, inbox, now) for member, inbox in zip(members, inboxes)]


def decide(
    member: ConvoyMember,
    frame: Frame,
    action: np.ndarray | PolicyFailure,
    bounds: ActionBounds,
    ranging: Ranging | None = None,
) -> Decision:
    """Step 3: check, clip and supervise the policy's ``action`` for ``frame`` (a
    ``PolicyFailure``, or anything but two numbers, is a policy error: stop)."""
    if isinstance(action, PolicyFailure):
        return stop(action.reason)
    shape = np.shape(action)
    if shape != (2,):
        return stop(f"action has shape {shape}, not (2,): [speed_mps, heading_change_rad]")
    try:
        speed, change = float(action[0]), float(action[1])
    except (TypeError, ValueError, IndexError) as exc:
        return stop(f"action {action!r} is not [speed, heading change]: {exc}")
    if not (math.isfinite(speed) and math.isfinite(change)):
        return stop(non_finite_reason(speed, change))
    clipped = np.array(bounds.clip(speed, change), dtype=np.float32)
    applied, mode = member.supervise(clipped, frame, ranging)
    return Decision(applied, mode)


def tick(
    member: ConvoyMember,
    policy: Actor | None,
    own: VehicleState,
    radio: Radio,
    now: float,
    bounds: ActionBounds,
    ranging: Ranging | None = None,
    may_send: bool = True,
    started: Callable[[], bool] | None = None,
) -> TickResult:
    """The whole tick for one member at time ``now`` (s): τ and the broadcast on ``radio``,
    its messages through ρ, then, once ``started()`` (asked once, after sensing; None:
    always), ``policy.act`` and the decision; ``policy`` None senses only (a leader)."""
    heard = _Heard(radio)
    (frame,) = exchange((member,), (own,), now, heard, (may_send,))
    broadcast = heard.sent
    if started is not None and not started():
        return TickResult(broadcast, frame, None, started=False)
    if policy is None:
        return TickResult(broadcast, frame, None)
    try:
        action = policy.act(frame.observation)
    except Exception as exc:  # noqa: BLE001 - the policy is foreign code: stop, report, go on
        return TickResult(broadcast, frame, stop(f"{type(exc).__name__}: {exc}"))
    return TickResult(broadcast, frame, decide(member, frame, action, bounds, ranging))
