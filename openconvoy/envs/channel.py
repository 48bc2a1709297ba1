"""The simulated V2V channel: broadcast messages over lossy, delayed links.

Every ordered (sender, receiver) pair is a link with its own loss model, made from one
``LossConfig`` (independent per receiver, as radio receptions are), and its own latency
draws. A broadcast offered at ``t_send`` reaches each receiver whose link did not drop it at
``t_send + delay``; ``deliver(now)`` hands out everything due by ``now`` in arrival order.
The delay is continuous, not whole ticks: a message that arrived ``d`` seconds before the
tick that delivers it is first ``advance``d by ``d`` (``advance_state``: as if the sender
had sampled its state ``d`` later, which is what unsynchronised control loops on real
vehicles do), so its age at first use is the delay drawn, as message ages measured on
vehicles are (phase between the loops + the link; ``fit-plant`` fits their distribution).
The loss models are the shared classes of ``openconvoy.comms.loss`` that vehicles apply at
the receiver with ``deploy --per``. All randomness comes from the Generator given to
``reset``, so a seed fixes the run. Bernoulli losses and latency jitter are counter-based
draws (``comms.loss.counter_uniform``) keyed by (channel key, sender, receiver, the
sender's broadcast number, purpose), so the batched simulator (``envs.vector.env``)
reproduces them with array operations.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np

from openconvoy.comms.loss import (
    Bernoulli,
    LossConfig,
    LossModel,
    NoLoss,
    counter_state_array,
    counter_uniform_array,
    counter_uniform_from,
)
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState

M = TypeVar("M")

ADVANCE_MIN_S = 1e-9
"""A message is advanced only when it waited longer than this (s) for its tick: a delay
of exactly k ticks (up to rounding) delivers the message as sent."""


def advance_kinematics(
    x: float, y: float, v: float, h: float, a: float, w: float, d: float
) -> tuple[float, float, float, float]:
    """A state moved on by ``d`` seconds at constant acceleration ``a`` (m/s², stopping at
    zero speed) and yaw rate ``w`` (rad/s): ``(x, y, speed, heading)`` in m, m/s, rad (ENU,
    heading wrapped to [-pi, pi)). ``envs.vector.channel`` compiles the same arithmetic."""
    v1 = v + a * d
    if (v > 0.0 and v1 < 0.0) or (v < 0.0 and v1 > 0.0):
        v1 = 0.0
    dist = 0.5 * (v + v1) * d
    h_mid = h + 0.5 * w * d
    return (
        x + dist * math.cos(h_mid),
        y + dist * math.sin(h_mid),
        v1,
        (h + w * d + math.pi) % (2.0 * math.pi) - math.pi,
    )


def advance_state(st: VehicleState, d: float, stamp_error: float = 0.0) -> VehicleState:
    """``st`` as its sender would have sent it ``d`` seconds later (``advance_kinematics``),
    stamped ``stamp_error`` seconds early (its clock running behind)."""
    if d > ADVANCE_MIN_S:
        x, y, v, h = advance_kinematics(st.x, st.y, st.speed, st.heading, st.accel, st.yaw_rate, d)
    else:
        d, x, y, v, h = 0.0, st.x, st.y, st.speed, st.heading
    return VehicleState(
        st.vehicle_id,
        st.t + d - stamp_error,
        x,
        y,
        v,
        h,
        st.accel,
        st.yaw_rate,
        st.length,
        st.width,
    )


DRAW_LOSS, DRAW_JITTER = 0, 1
"""Purpose words of the channel's counter-based draws."""

DRAW_BLOCK = 64
"""Most broadcasts per sender whose Bernoulli loss draws are made at once, as one array
operation (the same numbers as one ``counter_uniform`` per link and message)."""
DRAW_BUDGET = 4096
"""Most draws (broadcasts x receivers) one sender's block holds: a long convoy draws
fewer broadcasts ahead (a 1,000-vehicle convoy 4, not 64: 32 MB of held draws, not 512
MB), a short one ``DRAW_BLOCK``. The numbers drawn are the same either way."""


def draw_block_size(n_vehicles: int) -> int:
    """Broadcasts per sender drawn at once in a convoy of ``n_vehicles``."""
    return max(1, min(DRAW_BLOCK, DRAW_BUDGET // max(1, n_vehicles - 1)))


class Channel(Generic[M]):
    """Broadcast channel among ``n`` vehicles.

    Counters (numpy arrays built on access; plain lists inside, because the per-tick
    updates are a handful of integers and numpy indexing would cost more than the rest):
    ``sent[s, r]`` messages vehicle ``s`` offered to receiver ``r``; ``delivered[s, r]``
    messages that reached ``r`` (in-flight ones count once due); ``lost[s, r]`` messages
    the link ``s -> r`` dropped. ``delivered_to[r]``, ``lost_to[r]``: per-receiver totals.
    """

    def __init__(
        self,
        n_vehicles: int,
        loss: LossConfig | None = None,
        advance: Callable[[M, float, float], M] | None = None,
    ) -> None:
        if n_vehicles < 1:
            raise ConfigError(f"a channel needs at least one vehicle, got {n_vehicles}")
        self.n = n_vehicles
        self.config = loss or LossConfig()
        self._latency = self.config.latency
        probe = self.config.make()
        # Independent Bernoulli links are drawn for all receivers of a broadcast at once:
        # statistically the same as one draw per link, and much cheaper.
        self._bernoulli_per: float | None = None
        if isinstance(probe, NoLoss):
            self._bernoulli_per = 0.0
        elif isinstance(probe, Bernoulli):
            self._bernoulli_per = probe.per
        # Loss models with a state per link (Gilbert-Elliott); the diagonal is unused (a
        # vehicle does not hear itself). Bernoulli and perfect links draw counter-based
        # (``send``) and need none: N² objects and streams fewer at N vehicles.
        self._links: list[list[LossModel]] = (
            []
            if self._bernoulli_per is not None
            else [[self.config.make() for _ in range(n_vehicles)] for _ in range(n_vehicles)]
        )
        # Each link's delay model (its own distribution, or the common one).
        self._lat = [
            [self.config.link_latency(s, r) for r in range(n_vehicles)] for s in range(n_vehicles)
        ]
        self._instant = all(
            self._lat[s][r].instant for s in range(n_vehicles) for r in range(n_vehicles) if r != s
        )
        self._advance = advance
        self._block = draw_block_size(n_vehicles)
        # Links replaying a vehicle run's losses (LossConfig.lost_s) instead of drawing.
        self._replay = self.config.replay()
        # Messages carry their clock error from the send (the advance applies it).
        self._stamped = advance is not None and any(
            self._lat[s][r].stamped_off for s in range(n_vehicles) for r in range(n_vehicles)
        )
        self._others = [[r for r in range(n_vehicles) if r != s] for s in range(n_vehicles)]
        self._queue: list[tuple[float, int, int, int, M, float]] = []
        self._ready: list[tuple[int, int, M]] = []
        self.reset(np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        """Empty the channel, zero the counters, and draw all randomness from ``rng``."""
        self._rng = rng
        # First, so the per-link streams stay as they were; nothing draws from ``rng``
        # after them, so links without a model (Bernoulli) skip theirs.
        self.key = int(rng.integers(2**63))
        for s, row in enumerate(self._links):
            for r, model in enumerate(row):
                if r != s:
                    # Each link gets its own stream spawned from rng: adding a vehicle does
                    # not shift the draws of the others' links.
                    model.reset(np.random.default_rng(rng.integers(2**63)))
        n = self.n
        self._broadcasts = [0] * n
        self._delivered = [[0] * n for _ in range(n)]
        self._lost = [[0] * n for _ in range(n)]
        self.delivered_to = [0] * n
        self.lost_to = [0] * n
        self._queue.clear()
        self._ready.clear()
        self._seq = 0
        # Each link's draws are keyed by (channel key, sender, receiver, ...): those words
        # hashed once per episode, the message number and purpose per broadcast.
        # (One array operation: a per-link Python hash was seconds at 1,000 vehicles.)
        others = np.array(self._others, dtype=np.uint64).reshape(n, n - 1)
        senders = np.arange(n, dtype=np.uint64)[:, None]
        self._link_state_array = list(counter_state_array(self.key, senders, others))
        self._dropped: list[tuple[int, list[list[bool]]]] = [(-self._block, [])] * n

    @property
    def sent(self) -> np.ndarray:
        b = np.array(self._broadcasts, dtype=np.int64)
        out = np.repeat(b[:, None], self.n, axis=1)
        np.fill_diagonal(out, 0)
        return out

    @property
    def delivered(self) -> np.ndarray:
        return np.array(self._delivered, dtype=np.int64)

    @property
    def lost(self) -> np.ndarray:
        return np.array(self._lost, dtype=np.int64)

    def send(self, sender: int, msg: M, t: float) -> None:
        """Broadcast ``msg`` from ``sender`` at time ``t`` (s) to every other vehicle."""
        others = self._others[sender]
        number = self._broadcasts[sender]
        self._broadcasts[sender] += 1
        per = self._bernoulli_per
        lost_row = self._lost[sender]
        lost_to = self.lost_to
        if per == 0.0:
            receivers = others
        elif per is not None:
            first, block = self._dropped[sender]
            if not 0 <= number - first < self._block:
                first, block = self._dropped[sender] = (number, self._draw_block(sender, number))
            receivers = []
            for r, dropped in zip(others, block[number - first]):
                if dropped:
                    lost_row[r] += 1
                    lost_to[r] += 1
                else:
                    receivers.append(r)
        else:
            row = self._links[sender]
            receivers = []
            for r in others:
                if row[r].lost(t):
                    lost_row[r] += 1
                    lost_to[r] += 1
                else:
                    receivers.append(r)
        if self._replay:
            receivers = self._replayed(sender, t, receivers)
        if self._instant:
            self._ready.extend((r, sender, msg) for r in receivers)
            return
        lats = self._lat[sender]
        for r in receivers:
            lat = lats[r]
            if lat.jitter_s > 0.0 or lat.samples_s:
                state = int(self._link_state_array[sender][r - (r > sender)])
                arrival = t + lat.from_uniform(counter_uniform_from(state, number, DRAW_JITTER))
            else:
                arrival = t + lat.base_s
            err = lat.stamp_error(t) if self._stamped else 0.0
            heapq.heappush(self._queue, (arrival, self._seq, r, sender, msg, err))
            self._seq += 1

    def _replayed(self, sender: int, t: float, receivers: list[int]) -> list[int]:
        """``receivers`` with the replaying links' verdicts on the broadcast ``sender`` makes
        at ``t`` (s) in place of the drawn ones, the loss counters moved to match."""
        kept = set(receivers)
        for r in self._others[sender]:
            replay = self._replay.get((sender, r))
            if replay is None:
                continue
            drop = replay.lost(t)
            if drop and r in kept:
                kept.discard(r)
                self._lost[sender][r] += 1
                self.lost_to[r] += 1
            elif not drop and r not in kept:
                kept.add(r)
                self._lost[sender][r] -= 1
                self.lost_to[r] -= 1
        return [r for r in self._others[sender] if r in kept]

    def _draw_block(self, sender: int, first: int) -> list[list[bool]]:
        """Whether each link of ``sender`` drops its broadcasts ``first`` .. ``first +
        draw_block_size - 1``: ``[broadcast - first][receiver index]`` (Bernoulli)."""
        numbers = np.arange(first, first + self._block, dtype=np.uint64)
        states = self._link_state_array[sender]
        u = counter_uniform_array(states[None, :], numbers[:, None], DRAW_LOSS)
        return (u < self._bernoulli_per).tolist()

    def deliver(self, now: float) -> list[tuple[int, int, M]]:
        """Messages due by ``now`` (s), as ``(receiver, sender, msg)`` in arrival order;
        with an ``advance`` function each is advanced by how long it waited for ``now``."""
        out = self._ready
        self._ready = []
        q = self._queue
        if q:
            # A small epsilon so a delay of exactly k control periods lands on tick k.
            due = now + 1e-9
            advance = self._advance
            while q and q[0][0] <= due:
                arrival, _, r, s, msg, err = heapq.heappop(q)
                waited = now - arrival
                if advance is not None and (waited > ADVANCE_MIN_S or err != 0.0):
                    msg = advance(msg, waited, err)
                out.append((r, s, msg))
        delivered, delivered_to = self._delivered, self.delivered_to
        for r, s, _ in out:
            delivered[s][r] += 1
            delivered_to[r] += 1
        return out

    @property
    def in_flight(self) -> int:
        """Messages sent and not yet delivered (latency)."""
        return len(self._queue) + len(self._ready)

    def delivery_ratio(self) -> float:
        """Delivered / (delivered + lost) over all links; NaN before any message."""
        d = sum(self.delivered_to)
        total = d + sum(self.lost_to)
        return d / total if total else float("nan")
