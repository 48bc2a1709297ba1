"""The batched channel: Tx gates, loss, latency and delivery into the R^i buffers.

The same draws as ``envs.channel.Channel``: a Bernoulli loss is
``counter_uniform(key, sender, receiver, broadcast number, DRAW_LOSS) < per`` (compiled
here, bit-identical to ``comms.loss.counter_uniform``), a Gilbert-Elliott link keeps its
chain per ordered link (numpy, as ``GilbertElliott``), and a latency holds messages in a
ring of send slots until due, each pair's arrival ``t + latency + jitter * counter_uniform(key,
sender, receiver, broadcast number, DRAW_JITTER)`` (``Channel.send``; with latency samples
their quantile at that draw instead of the jitter), delivered in arrival order, advanced
by how long it waited for its tick (``envs.channel.advance_kinematics``). Loss is drawn on
``pairs``: the kept links (``link_counters="kept"``, the default: the draws that change a
delivery), or every ordered pair (``"all"``: the counters ``ConvoyEnv`` reports).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from openconvoy.comms.loss import (
    GE_ADVANCE,
    GE_INIT,
    GE_LOSS,
    SPLITMIX_GOLDEN,
    SPLITMIX_M1,
    SPLITMIX_M2,
    UNIT_53,
    GilbertElliott,
    Latency,
    LossConfig,
    counter_uniform_array,
)
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault
from openconvoy.core.gates import TriggerConfig
from openconvoy.envs.channel import ADVANCE_MIN_S, DRAW_JITTER, DRAW_LOSS
from openconvoy.envs.vector.jit import Bound, bare_inline, bare_kernel
from openconvoy.envs.vector.links import LinkTables
from openconvoy.envs.vector.math import norm
from openconvoy.envs.vector.plant import HEADING, SPEED, X, Y
from openconvoy.envs.vector.rx import RxBuffers, push_one

_G, _K1, _K2 = np.uint64(SPLITMIX_GOLDEN), np.uint64(SPLITMIX_M1), np.uint64(SPLITMIX_M2)
_S11, _S27, _S30, _S31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)


class Gate(NamedTuple):
    """The Tx gates' state and rule (``_tx_gate``): each vehicle's next check time
    ``next_check`` (s), its last broadcast ``last`` (t, x, y, speed, heading), messages
    ``sent``, the time its fault mutes it ``mute_from`` (s); the trigger's ``period`` (s),
    whether it is ``event``-triggered, its position and speed thresholds ``thr`` (m),
    ``sthr`` (m/s) and ``max_silence`` (s); out: who broadcasts now, ``send``."""

    next_check: np.ndarray
    last: np.ndarray
    sent: np.ndarray
    mute_from: np.ndarray
    period: float
    event: bool
    thr: float
    sthr: float
    max_silence: float
    send: np.ndarray


class Loss(NamedTuple):
    """The Bernoulli draws' words: each convoy's channel ``keys``, each sender's broadcast
    ``number``, each convoy's ``per``; ``zs`` (N,): scratch."""

    keys: np.ndarray
    number: np.ndarray
    per: np.ndarray
    zs: np.ndarray


class Pairs(NamedTuple):
    """The pairs the loss is drawn on: sender ``s``, receiver ``r``, kept ``link`` (-1:
    none), receiver-major."""

    s: np.ndarray
    r: np.ndarray
    link: np.ndarray


class Counts(NamedTuple):
    """Per receiver (B, N): messages ``lost_to`` it, ``delivered_to`` it, ``kept``."""

    lost_to: np.ndarray
    delivered_to: np.ndarray
    kept: np.ndarray


class Sent(NamedTuple):
    """This tick: who broadcasts, ``send`` (B, N), and which pair lost it, ``lost`` (B, P)."""

    send: np.ndarray
    lost: np.ndarray


class Flight(NamedTuple):
    """The messages in flight and their delays: the sender's ``latency`` and ``jitter``
    (s), each pair's delay quantiles ``samples`` (s) and how many, ``n_samples`` (0: the
    jitter); the stamps' clock error ``stamp_error`` (s) + ``stamp_drift`` * send time
    and each sender's staleness ``stamp_sender`` (s); per send slot each pair's
    ``arrival`` (s, inf: none), the slot's earliest ``first``, the senders' ``state`` and
    send time ``sent_t``; scratch ``due`` (S,) and ``advanced`` (6, B, N)."""

    latency: float
    jitter: float
    samples: np.ndarray
    n_samples: np.ndarray
    stamp_error: float
    stamp_drift: float
    stamp_sender: np.ndarray
    arrival: np.ndarray
    first: np.ndarray
    state: np.ndarray
    sent_t: np.ndarray
    due: np.ndarray
    advanced: np.ndarray


class VectorChannel:
    """Tx gates, message counters and loss of ``B`` convoys of ``N`` vehicles."""

    def __init__(
        self,
        B: int,
        links: LinkTables,
        losses: Sequence[LossConfig],
        trigger: TriggerConfig,
        faults: Sequence[Fault],
        dt: float,
        all_pairs: bool,
    ) -> None:
        N = links.N
        if any(c.lost_s for c in losses):
            raise ConfigError(
                "a channel replaying a vehicle run's losses (lost_s) is the scalar "
                "simulator's (openconvoy sim), not the batched one's"
            )
        self.B, self.N, self.trigger = B, N, trigger
        self.per = np.array([c.per for c in losses])
        self.loss = max(losses, key=lambda c: c.per)
        probe = self.loss.make()
        self.ge = probe if isinstance(probe, GilbertElliott) else None
        # Per convoy: the chain's mean good sojourn for its PER (PER 0: a perfect link).
        self.ge_good = np.array(
            [c.mean_burst_s * (1.0 - c.per) / c.per if c.per > 0 else np.inf for c in losses]
        )
        # Receiver-major, as the links are numbered: a tick's deliveries write each
        # receiver's counters, R^i buffers and trails in memory order (the draws do not
        # depend on the order). int32: a convoy has fewer than 2**31 pairs.
        if all_pairs:
            r, s = np.nonzero(~np.eye(N, dtype=bool))
            self.pair_s, self.pair_r = s.astype(np.int32), r.astype(np.int32)
            self.pair_link = links.link_of[s, r].astype(np.int32)
            del r, s
        else:
            self.pair_s, self.pair_r = links.link_s.astype(np.int32), links.link_r.astype(np.int32)
            self.pair_link = np.arange(links.L, dtype=np.int32)
        mute = [min([f.t_s - 1e-9 for f in faults if f.mutes and f.vehicle == i] or [np.inf])
                for i in range(N)]  # fmt: skip
        self.mute_from = np.array(mute, dtype=float)
        self.latency_s, self.jitter_s = self.loss.latency_s, self.loss.jitter_s
        self.stamp_error_s, self.stamp_drift = self.loss.stamp_error_s, self.loss.stamp_drift
        # Each sender's messages stamped older by its telemetry staleness (LossConfig).
        self.stamp_sender = np.array([self.loss.sender_staleness(i) for i in range(N)])
        # Each pair's delay distribution (``LossConfig.link_latency``): (P, Q) quantiles,
        # the first ``n_samples[p]`` used (0: the uniform jitter).
        # Built per sender (a link's model is its sender's unless ``link_latency_s``
        # names the link: those pairs looked up one by one), then spread over the pairs.
        plain = np.bincount(self.pair_s, minlength=N)  # each sender's pairs left its own
        own = {i: self.loss.link_latency(i, -1) for i in np.flatnonzero(plain).tolist()}
        special: dict[int, Latency] = {}
        for e in self.loss.link_latency_s:
            hit = np.flatnonzero((self.pair_s == int(e[0])) & (self.pair_r == int(e[1])))
            for p in hit.tolist():
                special.setdefault(p, self.loss.link_latency(int(e[0]), int(e[1])))
        for p in special:
            plain[self.pair_s[p]] -= 1
        used = [x for i, x in own.items() if plain[i] > 0] + list(special.values())
        q = max([len(x.samples_s) for x in used] + [1])
        delay = max([x.max_s for x in used] + [0.0])  # the longest a message is in flight
        instant = all(x.instant for x in used)
        row_s = np.zeros((N, q))
        row_n = np.zeros(N, dtype=np.int64)
        for i, x in own.items():
            row_s[i, : len(x.samples_s)] = x.samples_s
            row_n[i] = len(x.samples_s)
        # Read only by the delay queue: none (no rows) when every message is instant.
        spread = np.arange(0 if instant else len(self.pair_s))
        self.samples_s = row_s[self.pair_s[spread]]
        self.n_samples = row_n[self.pair_s[spread]]
        for p, x in special.items() if not instant else ():
            self.samples_s[p] = 0.0
            self.samples_s[p, : len(x.samples_s)] = x.samples_s
            self.n_samples[p] = len(x.samples_s)
        self.slots = 0 if instant else int(math.ceil(delay / dt)) + 3
        self._alloc()

    def _alloc(self) -> None:
        B, N, P, S = self.B, self.N, len(self.pair_s), self.slots
        self.keys = np.zeros(B, dtype=np.uint64)
        self.next_check = np.full((B, N), -np.inf)
        self.last_sent = np.full((5, B, N), np.nan)  # t, x, y, speed, heading
        self.msgs_sent, self.broadcasts, self.delivered_to, self.lost_to, self.msgs_kept = (
            np.zeros((B, N), dtype=np.int64) for _ in range(5)
        )
        self.send = np.zeros((B, N), dtype=bool)
        self._zs = np.zeros(N, dtype=np.uint64)  # each sender's first draw round (scratch)
        self.lost = np.zeros((B, P), dtype=bool)
        if self.ge is not None:  # per ordered link: key, state, packets offered, last time
            self.ge_key = np.zeros((B, N, N), dtype=np.uint64)
            self.ge_bad = np.zeros((B, N, N), dtype=bool)
            self.ge_n = np.zeros((B, N, N), dtype=np.int64)
            self.ge_t = np.full((B, N, N), np.nan)
        if S:  # in flight: per send slot, each pair's arrival time (inf: none), sender state
            self.q_arrival = np.full((S, B, P), np.inf)
            self.q_first = np.full((S, B), np.inf)  # a slot's earliest pending arrival
            self._due_slots = np.zeros(S, dtype=np.int64)
            self.q_state = np.zeros((S, 6, B, N))
            self.q_t = np.zeros((S, B, N))
            self._advanced = np.zeros((6, B, N))  # a delivered state, advanced
            self.flight = Flight(
                float(self.latency_s), float(self.jitter_s), self.samples_s, self.n_samples,
                float(self.stamp_error_s), float(self.stamp_drift), self.stamp_sender,
                self.q_arrival, self.q_first, self.q_state, self.q_t, self._due_slots,
                self._advanced,
            )  # fmt: skip
        c = self.trigger
        self.gate = Gate(
            self.next_check, self.last_sent, self.msgs_sent, self.mute_from, float(c.period_s),
            c.kind == "event", float(c.threshold_m), float(c.speed_threshold_mps),
            float(c.max_silence_s), self.send,
        )  # fmt: skip
        self.draws = Loss(self.keys, self.broadcasts, self.per, self._zs)
        self.pairs = Pairs(self.pair_s, self.pair_r, self.pair_link)
        self.counts = Counts(self.lost_to, self.delivered_to, self.msgs_kept)
        self.sent = Sent(self.send, self.lost)
        # One caller each, the arguments' types fixed by the env: typed once (``Bound``).
        self._gate, self._drop, self._drop_deliver = (
            Bound(_tx_gate),
            Bound(_bernoulli),
            Bound(_bernoulli_deliver),
        )
        self._enqueue, self._deliver, self._arrive = (
            Bound(_enqueue),
            Bound(_deliver),
            Bound(_arrive),
        )

    def reset(self, rows: np.ndarray) -> None:
        """Counters, gates and queues of convoys ``rows`` (bool (B,)) as new."""
        self.next_check[rows] = -np.inf
        for arr in (self.msgs_sent, self.broadcasts, self.delivered_to, self.lost_to):
            arr[rows] = 0
        self.msgs_kept[rows] = 0
        self.last_sent[:, rows] = np.nan
        if self.slots:
            self.q_arrival[:, rows] = np.inf
            self.q_first[:, rows] = np.inf

    def seed(self, b: int, rng: np.random.Generator) -> None:
        """Convoy ``b``'s channel keys from its channel generator, as ``Channel.reset``."""
        self.keys[b] = np.uint64(int(rng.integers(2**63)))
        if self.ge is None:
            return
        # Gilbert-Elliott: one seed per ordered link, the chain's key from that seed.
        N = self.N
        seeds = rng.integers(2**63, size=N * (N - 1)).tolist()
        keys = np.zeros((N, N), dtype=np.uint64)
        pairs = [(s, r) for s in range(N) for r in range(N) if r != s]
        for (s, r), seed in zip(pairs, seeds):
            keys[s, r] = np.uint64(int(np.random.default_rng(seed).integers(2**63)))
        p_bad = self.ge.mean_bad_s / (self.ge_good[b] + self.ge.mean_bad_s)
        self.ge_key[b] = keys
        self.ge_bad[b] = counter_uniform_array(keys, GE_INIT) < p_bad
        self.ge_n[b] = 0
        self.ge_t[b] = np.nan

    def transmit(
        self, t: np.ndarray, step: np.ndarray, own: np.ndarray, rows: np.ndarray, rx: RxBuffers
    ) -> None:
        """Tx gates, loss and delivery at ``t`` (B,), tick ``step`` (B,), of the own states
        ``own`` (6, B, N) for convoys ``rows``: what arrives now is pushed into ``rx``."""
        self._gate(t, rows, own, self.gate)
        pairs, counts, pushed = self.pairs, self.counts, rx.pushed
        if self.ge is None and self.slots == 0:  # instant Bernoulli: draw and deliver at once
            self._drop_deliver(self.draws, self.send, pairs, rows, t, own, counts, pushed)
            return
        if self.ge is not None:
            self.lost[:] = self._ge_lost(self.send, t)[:, self.pair_s, self.pair_r]
        else:
            self._drop(self.draws, self.send, pairs, rows, self.lost)
        instant = self.slots == 0
        if not instant:  # before the broadcasts are counted: the jitter draws' numbers
            self._enqueue(self.draws, self.sent, pairs, rows, t, step, own, self.flight)
        self.broadcasts += self.send
        self._deliver(self.sent, pairs, rows, t, own, counts, pushed, instant)
        if not instant:
            self._arrive(step, t, self.flight, pairs, counts, pushed)

    def _ge_lost(self, send: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``GilbertElliott.lost`` on every link whose sender broadcasts now, (B, N, N)."""
        ge = self.ge
        assert ge is not None
        N = self.N
        offered = send[:, :, None] & ~np.eye(N, dtype=bool)
        n = self.ge_n
        tt = t[:, None, None]
        last = self.ge_t
        offered &= (self.per > 0.0)[:, None, None]  # PER 0: a perfect link, no chain
        step = offered & ~np.isnan(last) & (tt > last)
        a, b = (1.0 / self.ge_good)[:, None, None], 1.0 / ge.mean_bad_s
        p_inf = a / (a + b)
        with np.errstate(invalid="ignore"):
            decay = np.exp(-(a + b) * (tt - last))
        p_bad = p_inf + (np.where(self.ge_bad, 1.0, 0.0) - p_inf) * decay
        moved = counter_uniform_array(self.ge_key, n, GE_ADVANCE) < p_bad
        self.ge_bad = np.where(step, moved, self.ge_bad)
        self.ge_t = np.where(offered, np.where(np.isnan(last), tt, np.fmax(last, tt)), last)
        p = np.where(self.ge_bad, ge.loss_bad, ge.loss_good)
        lost = offered & (p > 0.0) & (counter_uniform_array(self.ge_key, n, GE_LOSS) < p)
        self.ge_n = n + offered
        return lost


@bare_inline
def _mix(z):  # pragma: no cover - compiled
    """SplitMix64's finalizer on a uint64: one round of ``comms.loss.counter_state``
    (its ``_mix``), wrapping as uint64 arithmetic does."""
    z = (z ^ (z >> _S30)) * _K1
    z = (z ^ (z >> _S27)) * _K2
    return z ^ (z >> _S31)


@bare_inline
def counter_uniform4(key, w0, w1, w2, w3):  # pragma: no cover - compiled
    """``comms.loss.counter_uniform`` of ``(key, w0, w1, w2, w3)``, bit for bit."""
    z = _mix(key + _G + np.uint64(w0))
    z = _mix(z + _G + np.uint64(w1))
    z = _mix(z + _G + np.uint64(w2))
    z = _mix(z + _G + np.uint64(w3))
    return np.float64(z >> _S11) * UNIT_53


@bare_inline
def _draw_bits(zs, w1, w2):  # pragma: no cover - compiled
    """``counter_uniform4``'s last three rounds (``zs``: its first), ``w3 = DRAW_LOSS``:
    the uniform's 53 bits ``m`` (the uniform is ``m * 2**-53``): the bits of
    ``comms.loss.counter_uniform``."""
    z = _mix(zs + _G + np.uint64(w1))
    z = _mix(z + _G + np.uint64(w2))
    z = _mix(z + _G + np.uint64(DRAW_LOSS))
    return z >> _S11


@bare_inline
def loss_threshold(per):  # pragma: no cover - compiled
    """The integer ``c`` with ``m * 2**-53 < per`` exactly when ``m < c`` (``m`` an integer
    below 2**53; ``per * 2**53`` is exact): a loss draw compared without floats, as
    ``Channel._draw_block`` compares ``comms.loss.counter_uniform``'s float with ``per``."""
    return np.uint64(math.ceil(per * 9007199254740992.0))


@bare_kernel
def _tx_gate(t, rows, own, gate):  # pragma: no cover - compiled
    """``TxGate.should_send`` for every vehicle: who broadcasts now (``gate.send``)."""
    nc, last, sent, mute_from, send = (
        gate.next_check,
        gate.last,
        gate.sent,
        gate.mute_from,
        gate.send,
    )
    period, event, thr, sthr, max_silence = (
        gate.period,
        gate.event,
        gate.thr,
        gate.sthr,
        gate.max_silence,
    )
    for b in range(nc.shape[0]):
        tt = t[b]
        for i in range(nc.shape[1]):
            send[b, i] = False
            if not rows[b] or tt + 1e-9 < nc[b, i] or tt >= mute_from[i]:
                continue
            if nc[b, i] == -np.inf:
                nc[b, i] = tt
            while nc[b, i] <= tt + 1e-9:
                nc[b, i] += period
            ox, oy, ov = own[X, b, i], own[Y, b, i], own[SPEED, b, i]
            if event:
                lt = last[0, b, i]
                if not (math.isnan(lt) or tt - lt >= max_silence - 1e-9):
                    lv, lh, dt = last[3, b, i], last[4, b, i], tt - lt
                    px = last[1, b, i] + lv * math.cos(lh) * dt
                    py = last[2, b, i] + lv * math.sin(lh) * dt
                    if not (norm(ox - px, oy - py) > thr or abs(ov - lv) > sthr):
                        continue
            send[b, i] = True
            last[0, b, i], last[1, b, i], last[2, b, i] = tt, ox, oy
            last[3, b, i], last[4, b, i] = ov, own[HEADING, b, i]
            sent[b, i] += 1


@bare_kernel
def _bernoulli(draws, send, pairs, rows, lost):  # pragma: no cover - compiled
    """``Channel._draw_block``'s Bernoulli loss draws, one pair at a time: of every pair
    whose sender broadcasts (its broadcast number in ``draws.number``)."""
    keys, number, per, pair_s, pair_r = draws.keys, draws.number, draws.per, pairs.s, pairs.r
    for b in range(lost.shape[0]):
        for p in range(lost.shape[1]):
            s = pair_s[p]
            lost[b, p] = (
                rows[b]
                and per[b] > 0.0
                and send[b, s]
                and counter_uniform4(keys[b], s, pair_r[p], number[b, s], DRAW_LOSS) < per[b]
            )


@bare_kernel
def _bernoulli_deliver(draws, send, pairs, rows, t, own, counts, rx):  # pragma: no cover
    """``Channel.send`` and ``Channel.deliver`` of instant Bernoulli links (``_bernoulli``
    and ``_deliver``) in one walk over the pairs, receiver-major (``pairs.link``: each
    pair's link or -1): each receiver's counters, R^i buffers and trails are written in
    memory order, the senders' rows (``draws.zs``: scratch (N,), each broadcasting
    sender's first round of ``counter_uniform4``) stay in the first cache level. Counts
    the broadcasts. Property-tested against ``Channel`` and ``StateBuffer.push`` in
    ``tests/envs/vector/test_twins_channel.py``."""
    keys, number, per, zs = draws.keys, draws.number, draws.per, draws.zs
    pair_s, pair_r, pair_link = pairs.s, pairs.r, pairs.link
    lost_to, delivered_to, kept = counts.lost_to, counts.delivered_to, counts.kept
    keeps, newest = rx.keeps, rx.newest
    N = send.shape[1]
    for b in range(send.shape[0]):
        if not rows[b]:
            continue
        drawn = per[b] > 0.0
        thr = loss_threshold(per[b]) if drawn else np.uint64(0)
        tb = t[b]
        sending = False
        for s in range(N):
            if send[b, s]:  # counter_uniform4(key, s, r, nb, DRAW_LOSS): s's round once
                zs[s] = _mix(keys[b] + _G + np.uint64(s))
                sending = True
        if not sending:
            continue
        for p in range(len(pair_s)):
            s = pair_s[p]
            if not send[b, s]:
                continue
            r, link = pair_r[p], pair_link[p]
            miss = drawn and _draw_bits(zs[s], r, number[b, s]) < thr
            lost_to[b, r] += miss
            delivered_to[b, r] += 1 - miss
            if link < 0:
                continue
            kept[b, r] += 1 - miss
            if not keeps[link]:  # push_one of a time-only link (its count is never
                # read), inline and without a branch on the draw
                was = newest[b, link]
                newest[b, link] = was if miss else max(was, tb)
            elif not miss:
                push_one(rx, b, link, tb, own, s)
        for s in range(N):
            number[b, s] += send[b, s]


@bare_kernel
def _deliver(sent, pairs, rows, t, own, counts, rx, instant):  # pragma: no cover - compiled
    """``Channel.deliver``'s counters of this tick's broadcasts (``sent.lost``: the
    pairs' draws): losses counted; instant links also deliver now (``push_one``)."""
    send, lost, pair_s, pair_r, pair_link = sent.send, sent.lost, pairs.s, pairs.r, pairs.link
    lost_to, delivered_to, kept = counts.lost_to, counts.delivered_to, counts.kept
    for b in range(send.shape[0]):
        if not rows[b]:
            continue
        for p in range(len(pair_s)):
            s = pair_s[p]
            if not send[b, s]:
                continue
            r = pair_r[p]
            if lost[b, p]:
                lost_to[b, r] += 1
            elif instant:
                delivered_to[b, r] += 1
                link = pair_link[p]
                if link >= 0:
                    kept[b, r] += 1
                    push_one(rx, b, link, t[b], own, s)


@bare_inline
def _quantile_delay(samples, p, n, u):  # pragma: no cover - compiled
    """``comms.loss.quantile_delay`` of pair ``p``'s ``n`` quantiles, the same arithmetic."""
    if n == 1:
        return samples[p, 0]
    pos = u * (n - 1)
    k = int(pos)
    if k >= n - 1:
        return samples[p, n - 1]
    return samples[p, k] + (pos - k) * (samples[p, k + 1] - samples[p, k])


@bare_inline
def _advance(st, b, s, d, out):  # pragma: no cover - compiled
    """``envs.channel.advance_kinematics`` of sender ``s``'s state ``st[:, b, s]`` by ``d``
    seconds into ``out[:, b, s]`` (accel and yaw rate kept)."""
    x, y, v, h, a, w = st[0, b, s], st[1, b, s], st[2, b, s], st[3, b, s], st[4, b, s], st[5, b, s]
    v1 = v + a * d
    if (v > 0.0 and v1 < 0.0) or (v < 0.0 and v1 > 0.0):
        v1 = 0.0
    dist = 0.5 * (v + v1) * d
    h_mid = h + 0.5 * w * d
    out[0, b, s] = x + dist * math.cos(h_mid)
    out[1, b, s] = y + dist * math.sin(h_mid)
    out[2, b, s] = v1
    out[3, b, s] = (h + w * d + math.pi) % (2.0 * math.pi) - math.pi
    out[4, b, s], out[5, b, s] = a, w


@bare_kernel
def _enqueue(draws, sent, pairs, rows, t, step, own, fl):  # pragma: no cover - compiled
    """This tick's broadcasts into send slot ``step % S`` of ``fl`` (``Flight``): the
    senders' states, and each pair's arrival time (``Channel.send``'s, jitter or sample
    drawn on broadcast ``draws.number``; inf where not sent or lost), and the slot's
    earliest arrival ``fl.first``."""
    keys, number, send, lost, pair_s, pair_r = (
        draws.keys, draws.number, sent.send, sent.lost, pairs.s, pairs.r
    )  # fmt: skip
    latency, jitter, samples, n_samples = fl.latency, fl.jitter, fl.samples, fl.n_samples
    q_arrival, q_first, q_state, q_t = fl.arrival, fl.first, fl.state, fl.sent_t
    S, B, P = q_arrival.shape
    N = q_t.shape[2]
    for b in range(B):
        if not rows[b]:
            continue
        sl = step[b] % S
        q_first[sl, b] = np.inf
        for s in range(N):
            q_t[sl, b, s] = t[b]
            for f in range(6):
                q_state[sl, f, b, s] = own[f, b, s]
        for p in range(P):
            s = pair_s[p]
            if not send[b, s] or lost[b, p]:
                q_arrival[sl, b, p] = np.inf
                continue
            if n_samples[p] > 0:
                u = counter_uniform4(keys[b], s, pair_r[p], number[b, s], DRAW_JITTER)
                arrival = t[b] + (latency + _quantile_delay(samples, p, n_samples[p], u))
            elif jitter > 0.0:
                u = counter_uniform4(keys[b], s, pair_r[p], number[b, s], DRAW_JITTER)
                arrival = t[b] + (latency + u * jitter)
            else:
                arrival = t[b] + latency
            q_arrival[sl, b, p] = arrival
            q_first[sl, b] = min(q_first[sl, b], arrival)


@bare_kernel
def _arrive(step, t, fl, pairs, counts, rx):  # pragma: no cover - compiled
    """Deliver the messages of ``fl`` (``Flight``) due by ``t``, each pair's in arrival
    order (ties: the older send first), as ``Channel.deliver``: with jitter a later
    broadcast may overtake; one that waited for this tick is advanced by the wait (into
    ``fl.advanced``: scratch), and stamped with the senders' clock error ``stamp_error +
    stamp_drift * send time`` and the sender's staleness ``stamp_sender[s]`` (s).
    Only the send slots with something due (``fl.first``) are visited (``fl.due`` (S,):
    scratch)."""
    q_arrival, q_first, q_state, q_t = fl.arrival, fl.first, fl.state, fl.sent_t
    slots, advanced, stamp_sender = fl.due, fl.advanced, fl.stamp_sender
    stamp_error, stamp_drift = fl.stamp_error, fl.stamp_drift
    pair_s, pair_r, pair_link = pairs.s, pairs.r, pairs.link
    delivered_to, kept = counts.delivered_to, counts.kept
    S, B, P = q_arrival.shape
    for b in range(B):
        due = t[b] + 1e-9
        n_due = 0
        for back in range(S - 1, -1, -1):  # oldest send slot first
            sl = (step[b] - back) % S
            if q_first[sl, b] <= due:
                slots[n_due] = sl
                n_due += 1
        if n_due == 0:
            continue
        for p in range(P):
            s, r, link = pair_s[p], pair_r[p], pair_link[p]
            while True:
                first, first_arrival = -1, np.inf
                for k in range(n_due):
                    a = q_arrival[slots[k], b, p]
                    if a <= due and a < first_arrival:
                        first, first_arrival = slots[k], a
                if first < 0:
                    break
                q_arrival[first, b, p] = np.inf
                delivered_to[b, r] += 1
                if link >= 0:
                    kept[b, r] += 1
                    waited = t[b] - first_arrival
                    ts = q_t[first, b, s]
                    err = stamp_error + stamp_drift * ts + stamp_sender[s]
                    if waited > ADVANCE_MIN_S:
                        _advance(q_state[first], b, s, waited, advanced)
                        push_one(rx, b, link, ts + waited - err, advanced, s)
                    else:
                        push_one(rx, b, link, ts - err, q_state[first], s)
        for k in range(n_due):
            sl, pending = slots[k], np.inf
            for p in range(P):
                pending = min(pending, q_arrival[sl, b, p])
            q_first[sl, b] = pending
