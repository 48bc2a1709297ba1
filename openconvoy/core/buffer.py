"""R^i: for every vehicle heard, the last ``k`` states received (paper eq. 1), with trails.

Ages are measured on the receiver's clock against each message's own time stamp (the
sender's measurement time), as DESIGN.md defines message age.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState
from openconvoy.core.trail import Trail


class StateBuffer:
    """Last ``k`` states per sender id, newest first, plus each sender's trail."""

    def __init__(self, k: int, trail_spacing_m: float = 0.2) -> None:
        if k < 1:
            raise ConfigError(f"buffer depth k must be at least 1, got {k}")
        self.k = k
        self.trail_spacing_m = trail_spacing_m
        # Newest first, at most k: plain lists (a deque is ~600 bytes even for one state,
        # and a long all-predecessors convoy holds N²/2 of these).
        self._states: dict[int, list[VehicleState]] = {}
        self._trails: dict[int, Trail] = {}
        self._newest_t: dict[int, float] = {}  # each sender's newest time stamp

    def clear(self) -> None:
        self._states.clear()
        self._trails.clear()
        self._newest_t.clear()

    def push(self, state: VehicleState) -> None:
        """Store a received state. Out-of-order (older than the newest) states are ignored."""
        q = self._states.get(state.vehicle_id)
        if q is None:
            q = self._states[state.vehicle_id] = []
            self._trails[state.vehicle_id] = Trail(self.trail_spacing_m)
        elif q and state.t <= q[0].t:
            return
        q.insert(0, state)
        if len(q) > self.k:
            q.pop()
        self._newest_t[state.vehicle_id] = state.t
        self._trails[state.vehicle_id].add(state.x, state.y, state.heading, state.speed, state.t)

    def heard(self) -> list[int]:
        """Ids of every vehicle with at least one stored state."""
        return list(self._states)

    def latest(self, vehicle_id: int) -> VehicleState | None:
        q = self._states.get(vehicle_id)
        return q[0] if q else None

    def history(self, vehicle_id: int) -> list[VehicleState]:
        """Stored states of a vehicle, newest first (at most ``k``)."""
        return list(self._states.get(vehicle_id, ()))

    def states(self, vehicle_id: int) -> Sequence[VehicleState]:
        """``history`` without the copy (read only): empty when never heard."""
        return self._states.get(vehicle_id, ())

    def oldest_newest_t(self, vehicle_ids: Iterable[int]) -> float | None:
        """The oldest of the newest time stamps (s) of ``vehicle_ids`` (one at least),
        None if one of them was never heard."""
        try:
            return min(map(self._newest_t.__getitem__, vehicle_ids))
        except KeyError:
            return None

    def trail(self, vehicle_id: int) -> Trail | None:
        return self._trails.get(vehicle_id)

    def age(self, vehicle_id: int, now: float) -> float:
        """Seconds since the newest stored state was measured (inf if never heard)."""
        s = self.latest(vehicle_id)
        return float("inf") if s is None else max(0.0, now - s.t)
