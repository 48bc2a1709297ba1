"""The simulated V2V channel: broadcast messages over lossy, delayed links.

Every ordered (sender, receiver) pair is a link with its own loss model, made from one
``LossConfig`` (independent per receiver, as radio receptions are), and its own latency
draws. A broadcast offered at ``t_send`` reaches each receiver whose link did not drop it at
``t_send + delay``; ``deliver(now)`` hands out everything due by ``now`` in arrival order.
The loss models are the shared classes of ``openconvoy.comms.loss`` that vehicles apply at
the receiver with ``deploy --per``. All randomness comes from the Generator given to
``reset``, so a seed fixes the run.
"""

from __future__ import annotations

import heapq
from typing import Generic, TypeVar

import numpy as np

from openconvoy.comms.loss import Bernoulli, LossConfig, LossModel, NoLoss

M = TypeVar("M")


class Channel(Generic[M]):
    """Broadcast channel among ``n`` vehicles.

    Attributes:
        sent: ``sent[s, r]`` messages vehicle ``s`` offered to receiver ``r``.
        delivered: ``delivered[s, r]`` messages that reached ``r`` (including in flight ones
            once due).
        lost: ``lost[s, r]`` messages the link ``s -> r`` dropped.
    """

    def __init__(self, n_vehicles: int, loss: LossConfig | None = None) -> None:
        if n_vehicles < 1:
            raise ValueError(f"a channel needs at least one vehicle, got {n_vehicles}")
        self.n = n_vehicles
        self.config = loss or LossConfig()
        self._latency = self.config.latency
        # Loss models per link; the diagonal is unused (a vehicle does not hear itself).
        self._links: list[list[LossModel]] = [
            [self.config.make() for _ in range(n_vehicles)] for _ in range(n_vehicles)
        ]
        probe = self._links[0][0]
        # Independent Bernoulli links are drawn for all receivers at once: statistically the
        # same as one draw per link, and ~50x cheaper for long convoys.
        self._bernoulli_per: float | None = None
        if isinstance(probe, NoLoss):
            self._bernoulli_per = 0.0
        elif isinstance(probe, Bernoulli):
            self._bernoulli_per = probe.per
        self._instant = self._latency.base_s <= 0.0 and self._latency.jitter_s <= 0.0
        self._others = [np.array([r for r in range(n_vehicles) if r != s]) for s in range(n_vehicles)]
        self.sent = np.zeros((n_vehicles, n_vehicles), dtype=np.int64)
        self.delivered = np.zeros((n_vehicles, n_vehicles), dtype=np.int64)
        self.lost = np.zeros((n_vehicles, n_vehicles), dtype=np.int64)
        # Per-receiver totals kept alongside the matrices (cheap to read every tick).
        self.delivered_to = [0] * n_vehicles
        self.lost_to = [0] * n_vehicles
        self._queue: list[tuple[float, int, int, int, M]] = []
        self._ready: list[tuple[int, int, M]] = []
        self._seq = 0
        self.reset(np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the channel, zero the counters, and draw all randomness from ``rng``."""
        self._rng = rng
        for s, row in enumerate(self._links):
            for r, model in enumerate(row):
                if r != s:
                    # Each link gets its own stream spawned from rng: adding a vehicle does
                    # not shift the draws of the others' links.
                    model.reset(np.random.default_rng(rng.integers(2**63)))
        self.sent[:] = 0
        self.delivered[:] = 0
        self.lost[:] = 0
        self.delivered_to = [0] * self.n
        self.lost_to = [0] * self.n
        self._queue.clear()
        self._ready.clear()
        self._seq = 0

    def send(self, sender: int, msg: M, t: float) -> None:
        """Broadcast ``msg`` from ``sender`` at time ``t`` (s) to every other vehicle."""
        others = self._others[sender]
        self.sent[sender, others] += 1
        per = self._bernoulli_per
        if per is not None:
            if per > 0.0:
                keep = self._rng.random(len(others)) >= per
                receivers = others[keep]
                dropped = others[~keep]
                if len(dropped):
                    self.lost[sender, dropped] += 1
                    lost_to = self.lost_to
                    for r in dropped.tolist():
                        lost_to[r] += 1
            else:
                receivers = others
        else:
            row = self._links[sender]
            kept = []
            for r in others:
                if row[r].lost(t):
                    self.lost[sender, r] += 1
                    self.lost_to[r] += 1
                else:
                    kept.append(r)
            receivers = np.array(kept, dtype=int)
        if self._instant:
            for r in receivers.tolist():
                self._ready.append((r, sender, msg))
            return
        for r in receivers.tolist():
            arrival = t + self._latency.delay(self._rng)
            heapq.heappush(self._queue, (arrival, self._seq, r, sender, msg))
            self._seq += 1

    def deliver(self, now: float) -> list[tuple[int, int, M]]:
        """Messages due by ``now`` (s), as ``(receiver, sender, msg)`` in arrival order."""
        out = self._ready
        self._ready = []
        q = self._queue
        if q:
            # A small epsilon so a delay of exactly k control periods lands on tick k.
            due = now + 1e-9
            while q and q[0][0] <= due:
                _, _, r, s, msg = heapq.heappop(q)
                out.append((r, s, msg))
        if out:
            delivered_to = self.delivered_to
            for r, _s, _ in out:
                delivered_to[r] += 1
            senders = np.fromiter((s for _, s, _ in out), dtype=np.intp, count=len(out))
            receivers = np.fromiter((r for r, _, _ in out), dtype=np.intp, count=len(out))
            np.add.at(self.delivered, (senders, receivers), 1)
        return out

    @property
    def in_flight(self) -> int:
        """Messages sent and not yet delivered (latency)."""
        return len(self._queue) + len(self._ready)

    def delivery_ratio(self) -> float:
        """Delivered / (delivered + lost) over all links; NaN before any message."""
        d = int(self.delivered.sum())
        total = d + int(self.lost.sum())
        return d / total if total else float("nan")
