"""The batched channel's, receivers', forgers' and infos' twins against the scalar code
``ConvoyEnv`` runs, on random inputs (issue 21).

Each kernel of ``envs.vector.channel``, ``rx``, ``forge`` and ``measures.fill_infos`` is
run on a random state beside its reference: ``TxGate.should_send`` (with ``Fault.active``
muting), ``Channel.send``/``Channel.deliver`` (the channel key and broadcast numbers the
same, so the same counter draws), ``StateBuffer.push`` (the R^i buffers and trails),
``Authentication.deliver_forgeries`` and ``convoy_env.agent_infos``. The arithmetic is
the same on both sides (libm's ``cos``/``sin``; no ``hypot`` on a compared value except
the Tx gate's threshold, a strict comparison of random floats), so everything compares
exactly.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms.loss import LossConfig
from openconvoy.core.buffer import StateBuffer
from openconvoy.core.faults import Fault
from openconvoy.core.gates import TOPOLOGIES, TriggerConfig, TxGate
from openconvoy.core.member import MemberConfig
from openconvoy.core.state import VehicleState
from openconvoy.envs.channel import Channel, advance_state
from openconvoy.envs.convoy_env import agent_infos
from openconvoy.envs.forgery import Authentication
from openconvoy.envs.vector import channel as vchannel
from openconvoy.envs.vector import forge as vforge
from openconvoy.envs.vector import measures as vmeasures
from openconvoy.envs.vector import rx as vrx
from openconvoy.envs.vector.env import MODES
from openconvoy.envs.vector.links import LinkTables, build_links
from openconvoy.envs.vector.plant import COS_H, ROWS, SIN_H
from openconvoy.envs.vector.rx import HA, HC, HH, HS, HV, HX, HY, RxBuffers, T
from openconvoy.envs.vector.trail import CAPACITY, MIN_WINDOW, T_BASE, head_s
from openconvoy.envs.world import forged_states

FEW = settings(max_examples=30, deadline=None)
LENGTH, WIDTH = 4.5, 1.8
coord = st.floats(-500.0, 500.0)
speed = st.floats(0.0, 30.0)
heading = st.floats(-math.pi, math.pi)
vehicle = st.tuples(coord, coord, speed, heading, st.floats(-5.0, 3.0), st.floats(-0.5, 0.5))
"""x, y (m), speed (m/s), heading (rad), accel (m/s²), yaw rate (rad/s)."""
topology = st.sampled_from([t.replace(":K", ":2") for t in TOPOLOGIES])


def _own(states: list[tuple[float, ...]]) -> np.ndarray:
    """Convoy states as the plant's rows (B = 1), the heading's cosine and sine filled."""
    own = np.zeros((ROWS, 1, len(states)))
    for i, s in enumerate(states):
        own[:6, 0, i] = s
        own[COS_H, 0, i], own[SIN_H, 0, i] = math.cos(s[3]), math.sin(s[3])
    return own


def _state(i: int, t: float, s: tuple[float, ...]) -> VehicleState:
    """Vehicle ``i``'s state ``s`` (``vehicle``'s fields) at ``t`` (s), as the world makes it."""
    return VehicleState(i, t, *s, LENGTH, WIDTH)


# --- the Tx gate ---------------------------------------------------------------------------


wander = st.tuples(*[st.floats(-1.5, 1.5)] * 3, st.floats(-0.3, 0.3))
"""A tick's departure from dead reckoning: x, y (m), speed (m/s), heading (rad)."""


@FEW
@given(
    st.sampled_from(["periodic", "event"]),
    st.floats(0.05, 0.5),
    st.floats(0.1, 2.0),
    st.floats(0.1, 2.0),
    st.floats(0.2, 3.0),
    st.lists(vehicle, min_size=3, max_size=3),
    st.lists(st.tuples(st.floats(0.0, 0.3), st.booleans(),
                       st.lists(wander, min_size=3, max_size=3)),
             min_size=1, max_size=25),
    st.none() | st.floats(0.0, 3.0),
)  # fmt: skip
def test_tx_gate_is_tx_gate_should_send(
    kind: str,
    period: float,
    thr: float,
    sthr: float,
    silence: float,
    start: list[tuple[float, ...]],
    ticks: list[tuple[float, bool, list[tuple[float, ...]]]],
    mute_s: float | None,
) -> None:
    """``_tx_gate`` decides, counts and records each broadcast as ``TxGate.should_send``
    of each vehicle on the same states and times (the convoy stepped or not), vehicle 1
    muted from ``mute_s`` as ``ConvoyWorld`` mutes (``Fault.active``). The vehicles leave
    dead reckoning by about the thresholds, so the event trigger goes both ways."""
    config = TriggerConfig(kind, period, thr, sthr, silence)
    faults = [] if mute_s is None else [Fault("silent", 1, mute_s)]
    ch = vchannel.VectorChannel(1, build_links(MemberConfig(), 3), [LossConfig()], config,
                                faults, 0.1, False)  # fmt: skip
    gates = [TxGate(config) for _ in range(3)]
    sent = [0, 0, 0]
    t, states = 0.0, [list(s) for s in start]
    for dt, stepped, moves in ticks:
        t += dt
        for s, (ex, ey, ev, eh) in zip(states, moves):
            s[0] += s[2] * math.cos(s[3]) * dt + ex
            s[1] += s[2] * math.sin(s[3]) * dt + ey
            s[2], s[3] = s[2] + ev, s[3] + eh
        vchannel._tx_gate(np.array([t]), np.array([stepped]), _own(states), ch.gate)
        for i, g in enumerate(gates):
            muted = any(f.vehicle == i and f.active(t) for f in faults)
            want = stepped and not muted and g.should_send(_state(i, t, tuple(states[i])), t)
            sent[i] += want
            assert ch.gate.send[0, i] == want
        assert ch.msgs_sent[0].tolist() == sent


# --- loss and delivery -------------------------------------------------------------------


class Receivers:
    """What ``ConvoyWorld`` does with the channel's deliveries: each receiver's ρ keeps
    the messages of its links (``LinkTables``) in its ``StateBuffer``, counted."""

    def __init__(self, links: LinkTables, k: int, spacing_m: float) -> None:
        self.links = links
        self.buffers = [StateBuffer(k, spacing_m) for _ in range(links.N)]
        self.kept = [0] * links.N

    def take(self, delivered: list[tuple[int, int, VehicleState]]) -> None:
        """Keep ``(receiver, sender, msg)`` where a link holds it."""
        for r, s, msg in delivered:
            if self.links.link_of[s, r] >= 0:
                self.buffers[r].push(msg)
                self.kept[r] += 1


def assert_buffers_equal(rx: RxBuffers, ref: Receivers) -> None:
    """Each link's newest time, states (newest first) and trail in ``rx`` (convoy 0) are
    those of the receiver's ``StateBuffer``."""
    links = ref.links
    for ln in range(links.L):
        s, r = int(links.link_s[ln]), int(links.link_r[ln])
        buf = ref.buffers[r]
        history = buf.history(s)
        newest = history[0].t if history else -math.inf
        assert rx.newest[0, ln] == newest
        if not links.keeps_states[ln]:
            continue
        assert rx.hist_n[0, ln] == len(history)
        for j, m in enumerate(history):
            row = rx.hist[0, ln, j]
            want = (m.t, m.x, m.y, m.speed, m.heading, m.accel)
            assert tuple(row[[T, HX, HY, HV, HH, HA]]) == want
            assert (row[HC], row[HS]) == (math.cos(m.heading), math.sin(m.heading))
        tl = links.trail_of[ln]
        if tl >= 0 and history:
            trail = buf.trail(s)
            assert trail is not None and rx.trail_n[0, tl] == len(trail)
            head = (history[0].x, history[0].y)
            got = head_s(rx.tail, 0, tl, *head)
            assert abs(got - trail.head_s(head)) <= 1e-9 * (1.0 + abs(got))


def assert_counted(
    ch: vchannel.VectorChannel, sc: Channel, links: LinkTables, all_pairs: bool
) -> None:
    """Each receiver's messages lost and delivered in ``ch`` (convoy 0) are ``sc``'s on
    the pairs counted: every ordered pair (``link_counters="all"``) or the kept links."""
    counted = links.link_of >= 0 if not all_pairs else ~np.eye(links.N, dtype=bool)
    delivered, lost = (now - before for now, before in zip((sc.delivered, sc.lost), sc.before))
    assert ch.lost_to[0].tolist() == (lost * counted).sum(axis=0).tolist()
    assert ch.delivered_to[0].tolist() == (delivered * counted).sum(axis=0).tolist()
    if all_pairs:
        assert ch.lost_to[0].tolist() == sc.lost_to
        assert ch.delivered_to[0].tolist() == sc.delivered_to


def _convoy(topology: str, n: int, k: int) -> tuple[LinkTables, RxBuffers, Receivers]:
    """The links of ``topology`` in a convoy of ``n``, their batched and scalar receivers."""
    links = build_links(MemberConfig(topology=topology, k=k), n)
    return links, RxBuffers(1, links, k, 0.2, CAPACITY), Receivers(links, k, 0.2)


def _scalar_channel(n: int, config: LossConfig, seed: int, numbers: list[int]) -> Channel:
    """``Channel`` seeded as ``VectorChannel.seed`` with ``seed``, each sender ``s`` at
    broadcast number ``numbers[s]`` (earlier broadcasts sent and flushed), counters zeroed;
    ``before``: its delivered and lost matrices then."""
    ch: Channel = Channel(n, config, advance=advance_state)
    ch.reset(np.random.default_rng(seed))
    for s, count in enumerate(numbers):
        for _ in range(count):
            ch.send(s, _state(s, -1.0, (0.0,) * 6), -1.0)
    ch.deliver(1e9)
    ch.delivered_to, ch.lost_to = [0] * n, [0] * n
    ch.before = (ch.delivered, ch.lost)  # type: ignore[attr-defined]
    return ch


tick_sends = st.lists(st.tuples(st.lists(st.booleans(), min_size=6, max_size=6),
                                st.lists(vehicle, min_size=6, max_size=6)),
                      min_size=1, max_size=6)  # fmt: skip
"""Per tick: who broadcasts and every vehicle's state (the first ``n`` of each used)."""


def _scalar_tick(sc, ref, sends: list[bool], states: list[tuple[float, ...]], t: float) -> None:
    """The scalar side of a tick at ``t`` (s): ``Channel.send`` of each broadcast, then
    ``Channel.deliver`` into the reference buffers."""
    for s, (sending, state) in enumerate(zip(sends, states, strict=True)):
        if sending:
            sc.send(s, _state(s, t, state), t)
    ref.take(sc.deliver(t))


def _assert_same(ch, sc, ref, rx, links, all_pairs: bool) -> None:
    """The batched channel's counters, kept counts and R^i buffers are the scalar ones."""
    assert_counted(ch, sc, links, all_pairs)
    assert ch.msgs_kept[0].tolist() == ref.kept
    assert_buffers_equal(rx, ref)


@FEW
@given(
    st.integers(2, 6),
    topology,
    st.integers(1, 3),
    st.integers(0, 2**32),
    st.sampled_from([0.0, 0.3, 0.7, 1.0]) | st.floats(0.0, 1.0),
    st.lists(st.integers(0, 70), min_size=6, max_size=6),
    tick_sends,
    st.booleans(),
    st.booleans(),
)
def test_instant_delivery_is_channel_send_and_deliver(
    n: int,
    topo: str,
    k: int,
    seed: int,
    per: float,
    numbers: list[int],
    ticks: list[tuple[list[bool], list[tuple[float, ...]]]],
    fused: bool,
    all_pairs: bool,
) -> None:
    """Instant Bernoulli links, ``_bernoulli_deliver`` (fused) or ``_bernoulli`` then
    ``_deliver`` (as a Gilbert-Elliott channel counts), against ``Channel.send`` of each
    broadcast and ``Channel.deliver`` at each tick: the same losses (the counter draws on
    the same key and broadcast numbers, across a draw block's edge), counters and R^i
    buffers (``StateBuffer.push``, older messages ignored) and trails."""
    config = LossConfig(per=per)
    links, rx, ref = _convoy(topo, n, k)
    ch = vchannel.VectorChannel(1, links, [config], TriggerConfig(), [], 0.1, all_pairs)
    ch.seed(0, np.random.default_rng(seed))
    ch.broadcasts[0] = numbers[:n]
    sc = _scalar_channel(n, config, seed, numbers[:n])
    rows = np.array([True])
    for tick, (sends, states) in enumerate(ticks):
        t = 0.1 * tick
        own, tt = _own(states[:n]), np.array([t])
        ch.send[0] = sends[:n]
        if fused:
            vchannel._bernoulli_deliver(ch.draws, ch.send, ch.pairs, rows, tt, own, ch.counts,
                                        rx.pushed)  # fmt: skip
        else:
            vchannel._bernoulli(ch.draws, ch.send, ch.pairs, rows, ch.lost)
            vchannel._deliver(ch.sent, ch.pairs, rows, tt, own, ch.counts, rx.pushed, True)
            ch.broadcasts += ch.send
        _scalar_tick(sc, ref, sends[:n], states[:n], t)
        _assert_same(ch, sc, ref, rx, links, all_pairs)
        others = 1 - np.eye(n, dtype=np.int64)
        np.testing.assert_array_equal(sc.sent, ch.broadcasts[0][:, None] * others)


@FEW
@given(
    st.integers(2, 5),
    topology,
    st.integers(0, 2**32),
    st.floats(0.0, 0.6),
    st.floats(0.0, 0.35),
    st.floats(0.0, 0.3) | st.just(0.0),
    st.just(()) | st.lists(st.floats(0.0, 0.4), min_size=1, max_size=5).map(sorted).map(tuple),
    st.tuples(st.floats(-0.05, 0.05), st.floats(-1e-3, 1e-3)),
    st.lists(st.integers(0, 70), min_size=6, max_size=6),
    tick_sends,
    st.booleans(),
)
def test_delayed_delivery_is_channel_send_and_deliver(
    n: int,
    topo: str,
    seed: int,
    per: float,
    latency: float,
    jitter: float,
    samples: tuple[float, ...],
    stamp: tuple[float, float],
    numbers: list[int],
    ticks: list[tuple[list[bool], list[tuple[float, ...]]]],
    all_pairs: bool,
) -> None:
    """Links with a latency: ``_bernoulli``, ``_enqueue``, ``_deliver`` (losses only) and
    ``_arrive``, as ``VectorChannel.transmit`` calls them, against ``Channel.send`` and
    ``Channel.deliver`` with ``advance_state``: each message's arrival (the latency plus
    the jitter's or the samples' draw), delivered in arrival order once due, advanced by
    its wait and stamped with the clock error, into the same R^i buffers."""
    jitter = 0.0 if samples else jitter  # one or the other (LossConfig)
    config = LossConfig(per=per, latency_s=latency, jitter_s=jitter, latency_samples_s=samples,
                        stamp_error_s=stamp[0], stamp_drift=stamp[1])  # fmt: skip
    links, rx, ref = _convoy(topo, n, 3)
    ch = vchannel.VectorChannel(1, links, [config], TriggerConfig(), [], 0.1, all_pairs)
    ch.seed(0, np.random.default_rng(seed))
    ch.broadcasts[0] = numbers[:n]
    sc = _scalar_channel(n, config, seed, numbers[:n])
    rows = np.array([True])
    drain = [([False] * 6, ticks[-1][1])] * 9  # what is in flight (0.75 s at most) arrives
    for tick, (sends, states) in enumerate(ticks + drain):
        t, step = 0.1 * tick, np.array([tick])
        own, tt = _own(states[:n]), np.array([t])
        ch.send[0] = sends[:n]
        assert ch.slots > 0 or (latency == jitter == 0.0 and max(samples, default=0.0) == 0.0)
        vchannel._bernoulli(ch.draws, ch.send, ch.pairs, rows, ch.lost)
        instant = ch.slots == 0
        if not instant:
            vchannel._enqueue(ch.draws, ch.sent, ch.pairs, rows, tt, step, own, ch.flight)
        ch.broadcasts += ch.send
        vchannel._deliver(ch.sent, ch.pairs, rows, tt, own, ch.counts, rx.pushed, instant)
        if not instant:
            vchannel._arrive(step, tt, ch.flight, ch.pairs, ch.counts, rx.pushed)
        _scalar_tick(sc, ref, sends[:n], states[:n], t)
        _assert_same(ch, sc, ref, rx, links, all_pairs)
    assert sc.in_flight == 0


# --- the R^i buffers ---------------------------------------------------------------------


@FEW
@given(
    st.integers(1, 4),
    st.lists(st.tuples(st.floats(-0.2, 0.5), vehicle), min_size=1, max_size=40),
    st.sampled_from([0.08, 0.2, 1.0]),
)
def test_push_one_is_state_buffer_push(
    k: int, pushes: list[tuple[float, tuple[float, ...]]], spacing_m: float
) -> None:
    """``push_one`` onto a followed link (states kept, a trail) and a time-only link, of
    messages whose stamps go back and forth (older than the newest: ignored), against
    ``StateBuffer.push``: the same states newest first, newest time and trail."""
    # all-to-all among 4: links with trails, without, and one time-only (3 -> 1)
    links = build_links(MemberConfig(topology="all", k=k), 4)
    rx = RxBuffers(1, links, k, spacing_m, CAPACITY)
    ref = Receivers(links, k, spacing_m)
    assert not links.keeps_states.all() and 0 < links.T < links.L
    t = 0.0
    for step, (dt, (x, y, v, h, a, w)) in enumerate(pushes):
        t += dt
        s = step % 4  # each sender in turn, onto every link from it
        own = _own([(x, y, v, h, a, w)] * 4)
        for r in range(4):
            ln = links.link_of[s, r]
            if ln >= 0:
                vrx.push_one(rx.pushed, 0, ln, t, own, s)
                ref.take([(r, s, _state(s, t, (x, y, v, h, a, w)))])
        assert_buffers_equal(rx, ref)


@FEW
@given(st.lists(st.tuples(st.floats(0.0, 0.4), vehicle), min_size=1, max_size=3 * MIN_WINDOW),
       st.sampled_from([2, 4, CAPACITY // MIN_WINDOW]))  # fmt: skip
def test_rering_widens_to_the_ring_that_was_wide_from_the_start(
    pushes: list[tuple[float, tuple[float, ...]]], factor: int
) -> None:
    """``_rering`` (``RxBuffers.widen``) leaves each breadcrumb a narrow ring still holds
    where a ring as wide from the start holds it: the slot of its count since the reset."""
    links = build_links(MemberConfig(topology="predecessor"), 2)
    narrow = RxBuffers(1, links, 3, 0.2, MIN_WINDOW)
    wide = RxBuffers(1, links, 3, 0.2, MIN_WINDOW * factor)
    t = 0.0
    for dt, state in pushes:
        t += dt + 1e-3
        for rx in (narrow, wide):
            vrx.push_one(rx.pushed, 0, links.link_of[0, 1], t, _own([state] * 2), 0)
    narrow.widen(MIN_WINDOW * factor)
    base, n = int(narrow.tail[0, 0, T_BASE]), int(narrow.trail_n[0, 0])
    held = range(max(base + n - MIN_WINDOW, 0), base + n)
    slots = [c % (MIN_WINDOW * factor) for c in held]
    np.testing.assert_array_equal(narrow.trail[0, 0, slots], wide.trail[0, 0, slots])
    assert (narrow.trail_n == wide.trail_n).all()


# --- forged messages ---------------------------------------------------------------------


@FEW
@given(
    st.integers(2, 6),
    topology,
    st.lists(st.tuples(st.integers(0, 5), st.floats(0.0, 0.5)), min_size=1, max_size=3),
    st.lists(st.tuples(st.booleans(), st.lists(vehicle, min_size=6, max_size=6)),
             min_size=1, max_size=6),
)  # fmt: skip
def test_forge_is_authentication_deliver_forgeries(
    n: int,
    topo: str,
    forgers: list[tuple[int, float]],
    ticks: list[tuple[bool, list[tuple[float, ...]]]],
) -> None:
    """``_forge`` with authentication off against ``ConvoyWorld._forge``'s steps,
    ``forged_states`` of the active forgers then ``Authentication.deliver_forgeries``,
    each accepted message kept by the receivers' ρ: the same counts, R^i buffers and
    trails (the forged state is ``FORGED_AHEAD_M`` along the true heading)."""
    faults = [Fault("forge", v % n, t_s) for v, t_s in forgers]
    links, rx, ref = _convoy(topo, n, 3)
    fg = vforge.Forgers(faults, 1, n, 0.1, auth=False)
    auth = Authentication(n, required=False)
    kept = np.zeros((1, n), dtype=np.int64)
    for tick, (stepped, states) in enumerate(ticks):
        t = 0.1 * tick
        own = _own(states[:n])
        scratch = vforge.Forgeries(fg.vehicles, fg.t_s, np.zeros((6, 1, n)))
        vforge._forge(np.array([t]), np.array([stepped]), own, scratch, links.link_of, kept,
                      rx.pushed)  # fmt: skip
        if stepped:
            active = [f.vehicle for f in faults if f.active(t)]
            truth = SimpleNamespace(**{name: [s[j] for s in states[:n]] for j, name in
                                       enumerate(("x", "y", "speed", "heading"))})  # fmt: skip
            sizes = [LENGTH] * n, [WIDTH] * n
            claimed = forged_states(active, t, truth, *sizes)  # type: ignore[arg-type]
            inboxes: list[list[VehicleState]] = [[] for _ in range(n)]
            auth.deliver_forgeries(claimed, inboxes)
            ref.take([(r, m.vehicle_id, m) for r, inbox in enumerate(inboxes) for m in inbox])
        assert kept[0].tolist() == ref.kept
        assert_buffers_equal(rx, ref)
    assert auth.rejected == [0] * n


# --- the infos ---------------------------------------------------------------------------

maybe = st.floats(-50.0, 50.0) | st.just(math.nan)


@FEW
@given(
    st.integers(2, 6),
    st.lists(st.tuples(st.floats(0.0, 80.0), maybe, maybe, maybe, speed, st.floats(-5.0, 3.0),
                       st.floats(0.0, 30.0), st.floats(-0.3, 0.3), st.integers(0, 3),
                       *[st.integers(0, 40)] * 5),
             min_size=6, max_size=6),
    st.booleans(),
)  # fmt: skip
def test_fill_infos_is_agent_infos(n: int, rows: list[tuple], has_cmd: bool) -> None:
    """``fill_infos`` against ``convoy_env.agent_infos`` of a world holding the same
    values (NaN where the scalar info is None), ``msgs_offered`` against the others'
    broadcasts a ``Channel`` offers (its ``sent`` column), and the leader's keys against
    the leader's values the log row takes."""
    rows = rows[:n]
    col = list(zip(*rows))
    gap, desired, spacing_error, pred_age, v, a, cmd_v, cmd_dh, mode = col[:9]
    sent, received, kept, lost, errors = (list(c) for c in col[9:])
    record = SimpleNamespace(cmd_speed=cmd_v, cmd_heading_change=cmd_dh) if has_cmd else None
    sim = SimpleNamespace(
        t=1.0, truth=SimpleNamespace(speed=v, accel=a), gaps=gap[1:], desired=desired[1:],
        record=record, policy_errors=errors, modes=[MODES[m] for m in mode],
        collided=[False] * n, rx=received, lost=lost,
        members=[SimpleNamespace(msgs_sent=sent[i], msgs_received=kept[i]) for i in range(n)],
        frames=[SimpleNamespace(spacing_error_m=spacing_error[i], pred_msg_age_s=pred_age[i])
                for i in range(n)],
    )  # fmt: skip
    agents = [f"follower_{i}" for i in range(1, n)]
    want = agent_infos(sim, agents, n)  # type: ignore[arg-type]
    own = np.zeros((ROWS, 1, n))
    own[2, 0], own[4, 0] = v, a
    arr = [np.array([c]) for c in (desired, spacing_error)]
    rep = vmeasures.Reported(
        np.array([gap[1:]]), *arr, own, np.array([cmd_v]), np.array([cmd_dh]),
        np.array([has_cmd]), np.array([pred_age]), np.array([mode]),
        *[np.array([c], dtype=np.int64) for c in (sent, received, kept, lost, errors)],
    )  # fmt: skip
    out = vmeasures.info_arrays(1, n - 1)
    vmeasures.fill_infos(out, rep)
    fl, it, lf, li = out
    offered = _offered(sent)
    for f, agent in enumerate(agents):
        info = want[agent]
        for j, key in enumerate(vmeasures.FLOAT_KEYS):
            w = math.nan if info[key] is None else info[key]
            assert fl[j, 0, f] == w or (math.isnan(w) and math.isnan(fl[j, 0, f])), key
        for j, key in enumerate(vmeasures.INT_KEYS[:-1]):
            got = MODES[it[j, 0, f]] if key == "mode" else it[j, 0, f]
            assert got == info[key], key
        assert it[-1, 0, f] == offered[f + 1]
    leader_cmd = (cmd_v[0], cmd_dh[0]) if has_cmd else (math.nan, math.nan)
    np.testing.assert_array_equal(lf[:, 0], leader_cmd)
    assert li[:, 0].tolist() == [mode[0], sent[0], received[0], lost[0], offered[0]]


def _offered(broadcasts: list[int]) -> list[int]:
    """Messages every other vehicle offered each receiver, as a ``Channel`` counts them
    (``Channel.sent``'s column) when each vehicle broadcast ``broadcasts[s]`` times."""
    ch: Channel = Channel(len(broadcasts))
    for s, count in enumerate(broadcasts):
        for _ in range(count):
            ch.send(s, None, 0.0)
    return ch.sent.sum(axis=0).tolist()
