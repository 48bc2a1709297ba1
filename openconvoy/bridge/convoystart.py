"""The deploy runner's convoy start: waiting for the vehicles the topology needs.

A follower waits, armed and still, until it has heard the leader, the vehicle directly
ahead (the braking rule reads its gap: ``core.safety.verdict`` stops a follower that never
heard it, in simulation as here) and the predecessors its Rx gate keeps; a scenario-driven leader waits until it has heard every member (at most
``RunnerOptions.convoy_wait_s``), so the convoy starts moving together as in simulation.
"Heard" counts every vehicle message the V2V link delivered, before the Rx gate.

Before starting, the V2V link may refuse (``refusal``: a member that uses V2V
authentication differently, or a clock further off than the link's tolerance): a reason
given for ``REFUSE_AFTER_S`` on end refuses the start for good (``refused``, one line) and
the runner ends the run; while it has not lasted that long the vehicle waits. A deploy that
starts slowly on a loaded host reads, at its first tick, a backlog of its members' messages
that waited in its socket 1-2 s, and those alone read as clocks that far behind (the PX4
demo at load 8-17 on 2 cores: 5 of 8 runs refused at their first tick, vehicle 2's
"vehicle 0's clock is 1.35 s behind"); the fresh messages after it say otherwise. A leader
that starts without having heard every member says who and since when (D61).
"""

from __future__ import annotations

import time
from collections.abc import Callable

REFUSE_AFTER_S = 1.0
"""How long (s, monotonic) the V2V link's reason not to start must hold to refuse it."""


class ConvoyStart:
    """Who has been heard, and when this vehicle started moving.

    Args:
        vehicle_id: convoy index, 0 = leader; n_vehicles: the convoy's size.
        keeps: the member's Rx gate (``rx.keeps(j)``: whether messages of ``j`` are kept).
        leader_waits: whether a leader waits for the convoy (not passive, and
            ``leader_waits_for_convoy``); wait_s: the longest such wait (s).
        clock: the runner's monotonic clock (s).
        on_start: called once, when the start is recorded.
        refusal: why the convoy must not start ("" = it may), asked while waiting
            (``comms.v2v.V2V.start_refusal``); None: never refused.
        on_status: receives the leader's line about members never heard.
    """

    def __init__(
        self,
        vehicle_id: int,
        n_vehicles: int,
        keeps: Callable[[int], bool],
        *,
        leader_waits: bool,
        wait_s: float,
        clock: Callable[[], float],
        on_start: Callable[[], None] | None = None,
        refusal: Callable[[], str] | None = None,
        on_status: Callable[[str], None] | None = None,
    ) -> None:
        self.vehicle_id = vehicle_id
        self.n_vehicles = n_vehicles
        self.keeps = keeps
        self.leader_waits = leader_waits
        self.wait_s = wait_s
        self.clock = clock
        self.on_start = on_start
        self.refusal = refusal
        self.on_status = on_status
        self.refused = ""
        """Why the start was refused ("" = not refused)."""
        self._refusing_since: float | None = None  # when the reason now given was first
        self.heard: set[int] = set()
        self._said_wait: float | None = None  # when the last "waiting for" line went out
        self.t_start: float | None = None
        """Monotonic time (s) the convoy started moving; None before."""
        self.t_start_wall: float | None = None
        """The same on the shared clock (s)."""

    def heard_from(self, vehicle_id: int) -> None:
        self.heard.add(vehicle_id)

    def waiting_for(self, t_loop_start: float | None) -> list[int]:
        """Vehicles still unheard before this one may start (empty = go); the leader's wait
        counts from ``t_loop_start`` (the loop's first tick, monotonic s)."""
        if self.t_start is not None:
            return []
        i, n = self.vehicle_id, self.n_vehicles
        if i == 0:
            if not self.leader_waits:
                return []
            if (
                self.clock() - (t_loop_start if t_loop_start is not None else self.clock())
                > self.wait_s
            ):
                return []
            return [j for j in range(1, n) if j not in self.heard]
        need = {j for j in range(i) if self.keeps(j)}
        need.update((0, i - 1))
        return sorted(j for j in need if j not in self.heard)

    def update(self, now: float, wall: float, t_loop_start: float | None) -> bool:
        """Whether this vehicle still waits at monotonic ``now``; the first time it need not,
        the start is recorded (``t_start``, and ``wall`` as ``t_start_wall``)."""
        if self.refused:
            return True
        if self.t_start is None and self.refusal is not None:
            reason = self.refusal()
            if not reason:
                self._refusing_since = None
            else:
                if self._refusing_since is None:
                    self._refusing_since = now
                if now - self._refusing_since >= REFUSE_AFTER_S:
                    self.refused = reason
                return True
        missing = self.waiting_for(t_loop_start)
        waiting = bool(missing)
        if waiting:
            self._say_waiting(missing, now, t_loop_start)
        if not waiting and self.t_start is None:
            self._say_unheard(now, wall, t_loop_start)
            self.t_start, self.t_start_wall = now, wall
            if self.on_start is not None:
                self.on_start()
        return waiting

    SAY_AFTER_S = 3.0
    """A wait longer than this (s) is said, then again every ``SAY_EVERY_S``."""
    SAY_EVERY_S = 10.0

    def _say_waiting(self, missing: list[int], now: float, t_loop_start: float | None) -> None:
        """A long wait to start is never silent: who is missing, and for how long."""
        waited = now - (t_loop_start if t_loop_start is not None else now)
        due = self._said_wait is None or now - self._said_wait >= self.SAY_EVERY_S
        if self.on_status is None or waited < self.SAY_AFTER_S or not due:
            return
        self._said_wait = now
        who = ", ".join(str(j) for j in missing)
        after = (
            f"; starting anyway after {self.wait_s:g} s"
            if self.vehicle_id == 0 and self.leader_waits
            else ""
        )
        self.on_status(
            f"vehicle {self.vehicle_id}: waiting {waited:.0f} s for vehicle"
            f"{'s' if len(missing) > 1 else ''} {who} to be heard before starting{after}"
        )

    def _say_unheard(self, now: float, wall: float, t_loop_start: float | None) -> None:
        """The leader starting without having heard every member: who, and since when."""
        unheard = [j for j in range(1, self.n_vehicles) if j not in self.heard]
        if self.vehicle_id != 0 or not self.leader_waits or not unheard:
            return
        since = wall - (now - (t_loop_start if t_loop_start is not None else now))
        who = ", ".join(str(j) for j in unheard)
        line = (
            f"vehicle 0: no message from vehicle{'s' if len(unheard) > 1 else ''} {who} since "
            f"{time.strftime('%H:%M:%S', time.gmtime(since))} UTC ({now - (t_loop_start or now):.0f} s): "
            "starting anyway"
        )
        if self.on_status is not None:
            self.on_status(line)
