"""The deploy runner's V2V exchange: τ (broadcast the own state while it is known) and the
time-bounded receive, feeding the member's ρ.

Broadcasting pauses while the autopilot link is stale — without it the vehicle no longer
knows its own state, and a stale one with new timestamps would mislead the convoy — and
the pauses are announced and kept for the run's metadata. Receiving reads for at most
``RECEIVE_BUDGET`` of a loop period, so that a flood costs messages, never the loop's timing.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from openconvoy.bridge.convoystart import ConvoyStart
from openconvoy.core.member import ConvoyMember
from openconvoy.core.plans import Plan, PlanStore
from openconvoy.core.state import VehicleState

RECEIVE_BUDGET = 0.4
"""Share of a loop period the V2V receive may take per tick; datagrams beyond it wait for
the next tick (a flood of them costs messages, never the loop's timing)."""


class Exchange:
    """One vehicle's side of the V2V exchange, tick by tick.

    Args:
        member: the convoy member (its Tx and Rx gates); v2v: the endpoint
            (``runner.V2VEndpoint``); start_gate: told who was heard.
        rate_hz: control rate (Hz), for the receive budget.
        on_status: receives status lines (broadcast paused / resumed).
    """

    def __init__(
        self,
        member: ConvoyMember,
        v2v: Any,
        start_gate: ConvoyStart,
        *,
        rate_hz: float,
        on_status: Callable[[str], None],
    ) -> None:
        self.member = member
        self.v2v = v2v
        self.start_gate = start_gate
        self.rate_hz = rate_hz
        self.on_status = on_status
        self.abort = False
        """Whether an abort message was heard."""
        self.leader_complete = False
        """Whether the leader said (signed, when authenticating) it completed its scenario."""
        self._complete_sent = False
        self.broadcasting = True
        self.broadcast_pauses: list[list[float | None]] = []  # [wall from, wall to]
        self.plans = PlanStore(member.rx.keeps)
        """The plans heard (``core.plans``), beside the member's R^i."""
        self.plan: Plan | None = None
        """The own plan sent with the next state (``offer_plan``), if the policy plans."""

    def offer_plan(self, plan: Plan | None) -> None:
        """The own plan to send with the next broadcast state (None: none)."""
        self.plan = plan

    def send(self, state: VehicleState, wall: float) -> None:
        """Broadcast the own ``state`` (τ said so) at shared-clock time ``wall`` (s), with
        the own plan when there is a valid one (``core.tick.Radio``)."""
        self.v2v.send(state, wall)
        send_plan = getattr(self.v2v, "send_plan", None)
        if self.plan is not None and send_plan is not None and self.plan.valid():
            send_plan(self.plan, wall)

    def receive(self, wall: float) -> list[VehicleState]:
        """The vehicle states heard since the last tick, read for at most the receive
        budget, at shared-clock time ``wall`` (s) (``core.tick.Radio``); plans, an abort and
        the leader's completion are kept aside, and the start gate told who was heard."""
        inbox = []
        for msg in self.v2v.poll(wall, budget_s=RECEIVE_BUDGET / self.rate_hz):
            plan = getattr(msg, "plan", None)
            if plan is not None:
                self.plans.receive(plan)
            elif msg.abort:
                self.abort = True
            elif getattr(msg, "complete", False):
                self.leader_complete = True
            elif msg.state is not None:
                self.start_gate.heard_from(msg.state.vehicle_id)
                inbox.append(msg.state)
        take_alerts = getattr(self.v2v, "take_alerts", None)
        if take_alerts is not None:
            for line in take_alerts(wall):
                self.on_status(line)
        return inbox

    def announce_complete(self, wall: float) -> None:
        """The leader completed its scenario: say so to the convoy, once (the followers
        then end with exit 0 instead of waiting for messages that stopped, D62)."""
        send = getattr(self.v2v, "send_complete", None)
        if send is not None and not self._complete_sent:
            self._complete_sent = True
            send(wall)

    def delivered(self) -> int:
        """Vehicle messages the V2V link delivered (aborts are not traffic)."""
        c = self.v2v.counters
        return int(c.received - c.aborts - getattr(c, "plans", 0))

    def track_broadcast(self, known: bool, wall: float) -> None:
        """Whether the own state is ``known`` at shared-clock time ``wall`` (s): announce and
        record when broadcasting stops (autopilot link lost) and resumes."""
        if known == self.broadcasting:
            return
        self.broadcasting = known
        vid = self.member.vehicle_id
        if known:
            self.broadcast_pauses[-1][1] = wall
            self.on_status(f"vehicle {vid}: autopilot link back: broadcasting the own state again")
        else:
            self.broadcast_pauses.append([wall, None])
            self.on_status(
                f"vehicle {vid}: autopilot link lost: not broadcasting the own state "
                "(it is unknown now)"
            )
