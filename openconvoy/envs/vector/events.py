"""The batched env's safety events: each convoy's ``ConvoyEnv.safety_events``, on demand.

``ConvoyWorld`` appends ``(t s, vehicle, reason)`` when a follower's action is first
refused (``"policy error: ..."``), when its emergency stop latches (``"emergency stop:
..."``, with the bumper gap and closing speed it read) and when an injected fault first
becomes active (``"fault ..."``); in one tick the followers' events come in vehicle order,
then the faults' in their order. The batched tick keeps no list: ``vector.member.decide``
writes a latch's numbers into ``record`` (``EVENT_ROWS``, (9, B, N)) on the branch that
latches only (at most twice per follower and episode) and counts it in ``count``; a
fault's event follows from the clock alone (the first tick it is active at), so it costs
the tick nothing. ``SafetyEvents.of`` builds the tuples, strings and all, when asked.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from openconvoy.core.faults import Fault
from openconvoy.core.safety import BrakingGap
from openconvoy.core.tick import non_finite_reason
from openconvoy.envs.vector.member import EVENT_ROWS

Event = tuple[float, int, str]
"""(t s, vehicle, reason), as ``ConvoyWorld.safety_events``."""


def first_active_step(fault: Fault, dt: float) -> int:
    """The first tick ``k`` whose time ``k * dt`` (s) the fault is active at (as the
    world's clock computes it: ``step_count * dt``)."""
    k = max(0, math.ceil((fault.t_s - 1e-9) / dt))
    while k > 0 and fault.active((k - 1) * dt):
        k -= 1
    while not fault.active(k * dt):
        k += 1
    return k


class SafetyEvents:
    """The event record of ``B`` convoys of ``N`` vehicles ticking every ``dt`` s, with
    ``faults`` injected and ``rules[i]`` vehicle ``i``'s emergency rule (its reason
    text)."""

    def __init__(
        self, faults: Sequence[Fault], rules: Sequence[BrakingGap], B: int, N: int, dt: float
    ) -> None:
        self.record = np.full((len(EVENT_ROWS), B, N), np.nan)
        self.count = np.zeros(B, dtype=np.int64)
        self.rules = tuple(rules)
        self.dt = dt
        # ConvoyWorld records a fault once per episode, however often it is listed (a set).
        self.fault_steps = [(first_active_step(f, dt), f) for f in dict.fromkeys(faults)]

    def reset(self, which: np.ndarray) -> None:
        """Forget the episode of the convoys ``which`` (B,) bool."""
        self.record[:, which] = np.nan
        self.count[which] = 0

    def of(self, b: int, step_count: int) -> list[Event]:
        """Convoy ``b``'s events after ``step_count`` ticks of its episode, in
        ``ConvoyWorld``'s order with its reason strings."""
        keyed: list[tuple[tuple[float, int, int, int], Event]] = []
        if self.count[b]:
            keyed = self._members(b)
        for j, (k, f) in enumerate(self.fault_steps):
            if k < step_count:  # the tick at k * dt has been decided
                t = k * self.dt
                keyed.append(((t, 1, j, 0), (t, f.vehicle, f"fault {f}")))
        keyed.sort(key=lambda e: e[0])
        return [e for _, e in keyed]

    def finished(self, done: np.ndarray, step_count: np.ndarray) -> dict[int, list[Event]]:
        """``of`` each convoy ``done`` (B,) bool after ``step_count`` (B,) ticks, by convoy
        (an episode's end, often of many convoys at once: built only where needed)."""
        if self.fault_steps:
            which = np.flatnonzero(done).tolist()
        else:  # without faults only a latch makes an event
            which = np.flatnonzero(done & (self.count > 0)).tolist()
        out: dict[int, list[Event]] = {b: [] for b in np.flatnonzero(done).tolist()}
        for b in which:
            out[b] = self.of(b, int(step_count[b]))
        return out

    def _members(self, b: int) -> list[tuple[tuple[float, int, int, int], Event]]:
        """The followers' events of convoy ``b``, each with its sort key."""
        err_t, speed, change, stop_t, bumper, closing, ego, decel, accel = self.record[:, b]
        out = []
        for i in np.flatnonzero(~np.isnan(err_t)).tolist():
            t = float(err_t[i])
            why = non_finite_reason(float(speed[i]), float(change[i]))
            out.append(((t, 0, i, 0), (t, i, f"policy error: {why}")))
        for i in np.flatnonzero(~np.isnan(stop_t)).tolist():
            t = float(stop_t[i])
            reason = self.rules[i].reason(
                float(bumper[i]), float(closing[i]), float(ego[i]), float(decel[i]), float(accel[i])
            )
            out.append(((t, 0, i, 1), (t, i, "emergency stop: " + reason)))
        return out
