"""Shared plans: a vehicle's speed forecast, sent beside its state, kept beside R^i.

A ``Plan`` is what a model-predictive follower (``policies.mpc``) intends: its predicted
speed at ``t0 + k·step_s`` (k = 0..H; ``t0`` the time of validity on the shared clock), and
its actuator time constant. The sender broadcasts its newest plan whenever τ sends its state
(the same trigger); receivers keep the newest plan of every vehicle ρ keeps (``PlanStore``)
and hand them to their policy before it acts (``PlanningPolicy.observe_plans``).

When plans are lost, a receiver reads the last one shifted in time (it is indexed by
absolute time, so "shifting" is reading it at the later time; past its end the last speed
holds: Razzaghpour et al., ECC 2022) or falls back to constant-velocity dead reckoning from
the newest state (Razzaghpour et al., VTC 2021): ``MPCConfig.plan_fallback``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

MAX_PLAN_POINTS = 64
"""The most forecast points a plan carries (the wire format's limit)."""


@dataclass(frozen=True, slots=True)
class Plan:
    """Vehicle ``vehicle_id``'s speed forecast: ``speeds[k]`` (m/s) at ``t0 + k·step_s``
    (s, shared clock); ``tau_s`` its speed loop's time constant (s)."""

    vehicle_id: int
    t0: float
    step_s: float
    speeds: tuple[float, ...]
    tau_s: float = 0.0

    def valid(self) -> bool:
        """Finite, a positive step, 1..MAX_PLAN_POINTS non-negative speeds."""
        return (
            math.isfinite(self.t0)
            and math.isfinite(self.step_s)
            and self.step_s > 0.0
            and 1 <= len(self.speeds) <= MAX_PLAN_POINTS
            and all(math.isfinite(v) and v >= 0.0 for v in self.speeds)
            and math.isfinite(self.tau_s)
        )

    @property
    def end_s(self) -> float:
        """Time of the last forecast point (s)."""
        return self.t0 + (len(self.speeds) - 1) * self.step_s

    def speeds_at(self, times: np.ndarray) -> np.ndarray:
        """Forecast speeds (m/s) at ``times`` (s): linear between points, the first before
        ``t0``, the last after the end (the plan shifted in time)."""
        grid = self.t0 + self.step_s * np.arange(len(self.speeds))
        return np.interp(times, grid, np.asarray(self.speeds, dtype=float))

    def distance(self, t_from: float, t_to: float, samples: int = 8) -> float:
        """Distance (m) the forecast covers from ``t_from`` to ``t_to`` (s), trapezoids."""
        if t_to <= t_from:
            return 0.0
        ts = np.linspace(t_from, t_to, samples + 1)
        v = self.speeds_at(ts)
        return float(np.sum(0.5 * (v[1:] + v[:-1])) * (t_to - t_from) / samples)


class PlanHistory:
    """The plans a receiver has read of each vehicle, oldest first, kept for
    ``keep_s`` seconds after a newer one replaces them.

    A plan can arrive while the state message beside it is lost: the newest plan may then
    start (``t0``) after the newest state, and read alone it says nothing of the time
    between them but its first speed. Stitched, each instant is read from the newest plan
    valid by then (``speeds_at``, ``distance``), so the distance a vehicle covered since
    its newest state comes from the plans it shared over that time (issue 24: a
    follower under PER 0.8 took the leader at 1.08 m/s over a second in which it had
    slowed from 2 m/s, and fell 0.35 m behind its own estimate).
    """

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self._plans: dict[int, list[Plan]] = {}

    def clear(self) -> None:
        self._plans.clear()

    def add(self, plans: Mapping[int, Plan], now: float) -> None:
        """Keep each newest plan not held yet; drop those replaced before ``now − keep_s``
        (s)."""
        for vid, plan in plans.items():
            held = self._plans.setdefault(vid, [])
            if not held or plan.t0 > held[-1].t0:
                held.append(plan)
            while len(held) > 1 and held[1].t0 < now - self.keep_s:
                held.pop(0)

    def plans(self, vehicle_id: int) -> list[Plan]:
        """The plans held of ``vehicle_id``, oldest first."""
        return self._plans.get(vehicle_id, [])


def stitched_speeds_at(plans: Sequence[Plan], times: np.ndarray) -> np.ndarray:
    """Speeds (m/s) at ``times`` (s), each from the newest of ``plans`` (oldest first,
    at least one) whose ``t0`` is not after it, or from the oldest before them all."""
    times = np.asarray(times, dtype=float)
    which = _newest_index(plans, times)
    out = np.empty(times.shape)
    for k in np.unique(which):
        sel = which == k
        out[sel] = plans[int(k)].speeds_at(times[sel])
    return out


def stitched_distance(plans: Sequence[Plan], t_from: float, t_to: float) -> float:
    """Distance (m) from ``t_from`` to ``t_to`` (s) by ``stitched_speeds_at``: each plan
    over the time it was the newest (trapezoids, 8 per plan's piece)."""
    if t_to <= t_from:
        return 0.0
    cuts = [p.t0 for p in plans[1:] if t_from < p.t0 < t_to]
    edges = [t_from, *cuts, t_to]
    total = 0.0
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        # Each piece read from one plan: the one newest at its start.
        total += plans[int(_newest_index(plans, np.array([a]))[0])].distance(a, b)
    return total


def _newest_index(plans: Sequence[Plan], times: np.ndarray) -> np.ndarray:
    """For each of ``times`` (s), the index of the newest of ``plans`` (oldest first) with
    ``t0 <= t``, else 0 (the oldest)."""
    starts = np.array([p.t0 for p in plans])
    return np.maximum(np.searchsorted(starts, times, side="right") - 1, 0)


class PlanStore:
    """The newest plan of every vehicle heard, beside R^i; ``keeps`` is the member's ρ."""

    def __init__(self, keeps: Callable[[int], bool]) -> None:
        self.keeps = keeps
        self.plans: dict[int, Plan] = {}
        self.received = 0
        self.dropped = 0

    def clear(self) -> None:
        self.plans.clear()
        self.received = self.dropped = 0

    def receive(self, plan: Plan) -> bool:
        """Keep ``plan`` if ρ keeps its sender, it is well-formed and newer than the one
        held; otherwise count it dropped. True when kept."""
        if not plan.valid() or not self.keeps(plan.vehicle_id):
            self.dropped += 1
            return False
        held = self.plans.get(plan.vehicle_id)
        if held is not None and held.t0 >= plan.t0:
            self.dropped += 1
            return False
        self.plans[plan.vehicle_id] = plan
        self.received += 1
        return True

    def receive_all(self, plans: Iterable[Plan]) -> None:
        for p in plans:
            self.receive(p)


def braking_plan(vehicle: int, t: float, speed: float, decel: float, like: Plan | None) -> Plan:
    """Braking from ``speed`` (m/s) at ``decel`` (m/s², inf: at once) to rest from ``t``
    (s), on the grid of ``like`` (default 21 points 0.1 s apart)."""
    n, step, tau = (len(like.speeds), like.step_s, like.tau_s) if like else (21, 0.1, 0.0)
    v0 = max(speed, 0.0) if math.isfinite(speed) else 0.0
    a = decel if decel > 0.0 else math.inf
    return Plan(vehicle, t, step, (v0, *(max(v0 - a * k * step, 0.0) for k in range(1, n))), tau)


@runtime_checkable
class PlanningPolicy(Protocol):
    """A policy that shares plans: before each ``act`` the world hands it the plans it
    holds (vehicle id -> Plan), its own vehicle id and the time (s); after ``act``,
    ``plan()`` is the plan to broadcast with the next state (None: nothing to share)."""

    def observe_plans(self, plans: Mapping[int, Plan], vehicle_id: int, now: float) -> None: ...

    def plan(self) -> Plan | None: ...


def leader_plan(
    scenario: Any, preset: Any, t: float, speed: float, horizon: int, step_s: float
) -> Plan | None:
    """The leader's plan at ``t`` (s): the scenario driver's speed profile ahead (ramped at
    its limits, as ``PathScenario.leader_command`` ramps it) through the leader's speed lag
    and acceleration limits, from its ``speed`` now (m/s); None for a scenario without a
    speed profile. What a leader that knows its route's speed profile shares, in the simulator
    (``envs.plans``) and on vehicles (``bridge.leaderdrive``)."""
    profile = getattr(scenario, "speed_profile", None)
    if profile is None:
        return None
    cmd = float(getattr(scenario, "_cmd_speed", speed))
    s_now = float(getattr(scenario, "_s", 0.0))
    up = float(getattr(scenario, "ramp_accel_mps2", preset.accel_max_mps2))
    down = float(getattr(scenario, "ramp_decel_mps2", preset.decel_max_mps2))
    tau = max(preset.speed_lag_s if preset.speed_loop == "lag" else preset.drive_lag_s, 1e-3)
    delay = preset.actuation_delay_s
    h = 0.05
    sub = max(1, int(round(step_s / h)))
    h = step_s / sub
    v, s = float(speed), s_now
    out = [v]
    queue = [cmd] * max(1, int(round(delay / h)))
    for k in range(horizon):
        for j in range(sub):
            tk = t + (k * sub + j) * h
            target = float(profile(tk, s))
            cmd += min(max(target - cmd, -down * h), up * h)
            queue.append(cmd)
            u = queue.pop(0)
            dv = min(max((u - v) / tau, -preset.decel_max_mps2), preset.accel_max_mps2) * h
            v = max(v + dv, 0.0)
            s += v * h
        out.append(v)
    if not all(math.isfinite(x) for x in out):
        return None
    return Plan(0, t, step_s, tuple(out), tau)
