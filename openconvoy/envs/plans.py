"""Plans over the simulated V2V channel (``core.plans``), beside the states.

``PlanExchange`` is the world's part: every vehicle's newest plan goes out whenever τ sends
its state (the same trigger), over its own ``Channel`` with the run's ``LossConfig`` (the
plan is its own message on the wire, so its losses are drawn apart from the state's), and
each receiver keeps what ρ keeps in its ``PlanStore``. ``PlanRelay`` is the runner's part:
before the policies act it hands each planning policy the plans its vehicle holds, after
they act it takes their new plans to send.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.core.member import ConvoyMember
from openconvoy.core.plans import Plan, PlanningPolicy, PlanStore, braking_plan
from openconvoy.core.plans import leader_plan as leader_plan  # re-export: its home is core
from openconvoy.envs.channel import Channel


class PlanExchange:
    """Plans of ``members`` (one per vehicle) over a lossy channel made from ``loss``."""

    def __init__(self, members: Sequence[ConvoyMember], loss: LossConfig) -> None:
        self.members = list(members)
        n = len(self.members)
        self.channel: Channel[Plan] = Channel(n, loss)
        self.stores = [PlanStore(m.rx.keeps) for m in self.members]
        self.outgoing: list[Plan | None] = [None] * n
        self.sent = 0
        self.leader: Callable[[float], Plan | None] | None = None
        """The leader's plan at a time (s), when the world can say what its driver intends."""

    def reset(self, rng: np.random.Generator) -> None:
        self.channel.reset(rng)
        for s in self.stores:
            s.clear()
        self.outgoing = [None] * len(self.members)
        self.sent = 0

    def offer(self, vehicle: int, plan: Plan | None) -> None:
        """Vehicle ``vehicle``'s newest plan (sent with its next state)."""
        self.outgoing[vehicle] = plan

    def send(
        self, vehicle: int, t: float, mode: str = "coop", speed: float = 0.0, decel: float = 1.0
    ) -> None:
        """τ sent ``vehicle``'s state at ``t`` (s): its plan goes too, if it has one. A
        vehicle whose commands are not its policy's (``mode`` other than ``coop``: a
        ladder rung, an emergency stop, a fault) shares what it will do instead: brake
        from ``speed`` (m/s) at ``decel`` (m/s²) to rest (``braking_plan``)."""
        plan = self.outgoing[vehicle]
        if vehicle == 0 and self.leader is not None:
            plan = self.leader(t)
        if mode != "coop":
            plan = braking_plan(vehicle, t, speed, decel, plan)
        if plan is not None:
            self.channel.send(vehicle, plan, t)
            self.sent += 1

    def deliver(self, t: float) -> None:
        """Plans due by ``t`` (s) into the receivers' stores (ρ applied there)."""
        for r, _, plan in self.channel.deliver(t):
            self.stores[r].receive(plan)

    def held(self, vehicle: int) -> Mapping[int, Plan]:
        """The plans ``vehicle`` holds (vehicle id -> newest plan)."""
        return self.stores[vehicle].plans


class PlanRelay:
    """Carries plans between a ``ConvoyEnv``'s world and the planning policies among
    ``policies`` (agent name -> policy); inert when none plans."""

    def __init__(self, env: Any, policies: Mapping[str, Any]) -> None:
        self.env = env
        self.planning = {
            a: p
            for a, p in policies.items()
            if isinstance(p, PlanningPolicy) and getattr(getattr(p, "mpc", None), "use_plans", True)
        }
        self.observers = {a: p for a, p in policies.items() if isinstance(p, PlanningPolicy)}
        if self.observers:
            sim = env.sim
            sim.enable_plans()
            first = next(iter(self.observers.values()))
            mpc = getattr(first, "mpc", None)
            if mpc is not None and sim.plans is not None:
                horizon, step = mpc.horizon, mpc.step_s
                sim.plans.leader = lambda t: leader_plan(
                    sim.scenario, sim.presets[0], t, sim.truth.speed[0], horizon, step
                )

    def _index(self, agent: str) -> int:
        return int(self.env.possible_agents.index(agent)) + 1

    def before_act(self) -> None:
        """Hand each planning policy its vehicle's plans and the time."""
        sim = self.env.sim
        if sim.plans is None:
            return
        for a, p in self.observers.items():
            i = self._index(a)
            p.observe_plans(sim.plans.held(i), i, sim.t)

    def after_act(self) -> None:
        """Take each planning policy's new plan to send with its next state."""
        sim = self.env.sim
        if sim.plans is None:
            return
        for a, p in self.planning.items():
            sim.plans.offer(self._index(a), p.plan())
