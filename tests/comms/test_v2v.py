"""The V2V link's logic over an in-memory bus: filtering, counting, loss, compat, abort,
a member consuming a mixed J2735 + compat stream, and the receiver fuzz."""

from __future__ import annotations

import math
import random
from dataclasses import replace

import numpy as np
import pytest
from comms_testdata import load_vectors
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as compat
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.loss import LossConfig
from openconvoy.comms.mapping import state_to_core
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.tempids import TempIds, derive_temp_id
from openconvoy.comms.v2v import POLL_CHUNK, V2V, Counters, LinkConfig, Receiver, Sender
from openconvoy.core.member import ConvoyMember, MemberConfig
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("test", 3)


def _link(bus, index, bus4=None, **kw):
    cfg = LinkConfig(iface="mem", compat=bus4 is not None)
    return V2V(
        cfg,
        IDS,
        ORIGIN,
        index,
        transport=bus.endpoint(f"v{index}"),
        compat_transport=bus4.endpoint(f"v{index}") if bus4 is not None else None,
        **kw,
    )


def _state(i, t, x=None):
    return VehicleState(i, t, -15.0 * i if x is None else x, 2.0, 1.0, 0.1, 0.2, 0.0, 0.5, 0.3)


def _balanced(c: Counters) -> bool:
    return c.datagrams == (
        c.received
        + c.malformed
        + c.filtered
        + c.echoes
        + c.duplicates
        + c.rejected
        + c.lost
        + c.shed
        + c.replays
    )


def test_temp_ids_default_override_and_collision():
    ids = TempIds("lab", 3)
    assert ids.id_of(1) == derive_temp_id("lab", 1) and len(ids.id_of(1)) == 4
    assert TempIds("lab", 3).id_of(2) == ids.id_of(2)  # deterministic
    assert TempIds("other", 3).id_of(0) != ids.id_of(0)
    assert ids.index_of(ids.id_of(2)) == 2 and ids.index_of(b"\0\0\0\0") is None
    over = TempIds("lab", 3, {1: "0x0A0B0C0D"})
    assert over.id_of(1) == bytes.fromhex("0a0b0c0d") and over.index_of(over.id_of(1)) == 1
    with pytest.raises(ValueError, match="collide"):
        TempIds("lab", 3, {0: "01020304", 2: "01020304"})
    with pytest.raises(ValueError, match="8 hex digits"):
        TempIds("lab", 3, {0: "0102"})
    with pytest.raises(IndexError):
        ids.id_of(3)


def test_three_links_hear_each_other_not_themselves():
    bus = MemoryBus()
    links = [_link(bus, i) for i in range(3)]
    for k in range(5):
        for i, link in enumerate(links):
            assert link.send(_state(i, 100.0 + 0.1 * k), 100.0 + 0.1 * k)
    for i, link in enumerate(links):
        got = link.poll(100.55)
        assert sorted(r.sender for r in got) == sorted([x for x in range(3) if x != i] * 5)
        c = link.counters
        assert (c.sent, c.received, c.echoes, c.malformed, c.filtered) == (5, 10, 5, 0, 0)
        assert _balanced(c)
        r = got[-1]
        assert r.source == "j2735" and not r.abort
        assert r.state.vehicle_id == r.sender
        assert r.state.x == pytest.approx(-15.0 * r.sender, abs=6e-3)
        assert r.state.t == pytest.approx(100.4, abs=1e-3)
        assert r.age == pytest.approx(0.15, abs=1e-3)
        assert r.temp_id == IDS.id_of(r.sender) and r.msg_cnt == 4


def test_msg_cnt_wraps_at_128():
    bus = MemoryBus()
    a, b = _link(bus, 0), _link(bus, 1)
    counts = []
    for k in range(130):
        a.send(_state(0, float(k)), float(k))
        counts += [r.msg_cnt for r in b.poll(float(k))]
    assert counts[:3] == [0, 1, 2] and counts[126:] == [126, 127, 0, 1]


def test_foreign_and_malformed_traffic_is_counted_not_delivered():
    bus = MemoryBus()
    link = _link(bus, 0)
    foreign = state_to_core(_state(1, 10.0), ORIGIN, b"\x99\x99\x99\x99", 0)
    bus.inject(j.encode_frame(foreign))
    for v in load_vectors():  # real-world BSMs from other equipment: foreign, valid
        bus.inject(bytes.fromhex(v["hex"]))
    bus.inject(b"\x00\x13" + bytes(40))  # a SPaT, not a BSM
    bus.inject(b"hello")
    bus.inject(b"")
    bus.inject(b'{"time": 1}')
    assert link.poll(10.0) == []
    c = link.counters
    assert c.filtered == 55 and c.malformed == 4 and c.received == 0 and _balanced(c)


def test_receiver_side_loss_is_per_link_and_seeded():
    def run(seed):
        bus = MemoryBus()
        tx = [_link(bus, 1), _link(bus, 2)]
        rx = _link(bus, 0, loss=LossConfig(per=0.3), rng=np.random.default_rng(seed))
        got = []
        for k in range(1000):
            for i, link in enumerate(tx, start=1):
                link.send(_state(i, k * 0.1), k * 0.1)
            got += [(r.sender, r.msg_cnt) for r in rx.poll(k * 0.1)]
        return got, rx.counters

    got, c = run(5)
    assert got == run(5)[0]  # same seed, same drops
    assert got != run(6)[0]
    assert c.received + c.lost == 2000 and _balanced(c)
    # 2000 Bernoulli(0.7) draws: 99 % band is 0.7 +- 2.576 * sqrt(0.21 / 2000) = +- 0.026
    assert abs(c.received / 2000 - 0.7) < 0.0264
    per_link = [sum(1 for s, _ in got if s == i) / 1000 for i in (1, 2)]
    assert all(abs(p - 0.7) < 0.0374 for p in per_link)


def test_sender_side_loss_drops_for_everyone():
    bus = MemoryBus()
    tx = _link(bus, 0, loss=LossConfig(per=0.5), drop_at="sender", rng=np.random.default_rng(1))
    rx1, rx2 = _link(bus, 1), _link(bus, 2)
    for k in range(400):
        tx.send(_state(0, k * 0.1), k * 0.1)
    got1 = [r.msg_cnt for r in rx1.poll(40.0)]
    got2 = [r.msg_cnt for r in rx2.poll(40.0)]
    assert got1 == got2  # one draw per message, not per receiver
    assert tx.counters.sent + tx.counters.lost == 400
    assert tx.counters.sent == len(got1) and abs(len(got1) / 400 - 0.5) < 0.065
    assert tx.metadata["drop_at"] == "sender" and tx.metadata["loss"]["per"] == 0.5
    with pytest.raises(ValueError, match="drop_at"):
        _link(bus, 0, drop_at="middle")


def test_sending_another_vehicles_state_is_an_error():
    with pytest.raises(ValueError, match="vehicle 2"):
        _link(MemoryBus(), 0).send(_state(2, 0.0), 0.0)


def test_abort_from_operator_and_vehicle():
    bus, bus4 = MemoryBus(), MemoryBus()
    links = [_link(bus, i, bus4, loss=LossConfig(per=1.0)) for i in range(3)]
    bus.inject(compat.make_abort(50.0))  # an operator on the IPv6 group
    got = links[1].poll(50.1)
    assert len(got) == 1 and got[0].abort and got[0].sender == -1 and got[0].state is None
    links[0].send_abort(51.0, _state(0, 51.0))  # a vehicle: on both groups
    got = links[2].poll(51.05)
    # the operator's, then vehicle 0's twice (both groups): never lost, even at PER 1
    assert [(r.abort, r.sender) for r in got] == [(True, -1), (True, 0), (True, 0)]
    assert got[1].state.vehicle_id == 0 and got[1].state.x == pytest.approx(0.0, abs=1e-6)
    assert [r.sender for r in links[0].poll(51.05)] == [-1]
    assert links[0].counters.echoes == 2
    assert links[2].counters.aborts == 3


def test_compat_twin_is_a_duplicate_but_legacy_vehicles_are_heard():
    bus, bus4 = MemoryBus(), MemoryBus()
    ours = [_link(bus, i, bus4) for i in range(2)]
    for k in range(3):
        t = 10.0 + 0.1 * k
        ours[0].send(_state(0, t), t)
        bus4.inject(compat.encode_state(_state(2, t), ORIGIN))  # legacy vehicle 2: JSON only
    got = ours[1].poll(10.25)
    assert sorted((r.sender, r.source) for r in got) == [(0, "j2735")] * 3 + [(2, "compat")] * 3
    c = ours[1].counters
    assert c.duplicates == 3 and c.received == 6 and _balanced(c)


def test_member_consumes_mixed_j2735_and_compat_stream():
    """A follower's ConvoyMember fed from V2V: vehicle 0 speaks J2735 (ours), vehicle 1
    runs the original implementation (compat JSON only). Both land in R^i alike."""
    bus, bus4 = MemoryBus(), MemoryBus()
    leader = _link(bus, 0, bus4)
    me = _link(bus, 2, bus4)
    member = ConvoyMember(2, 3, MemberConfig(topology="all-predecessors"))
    sources = set()
    for k in range(20):
        t = 200.0 + 0.1 * k
        leader.send(_state(0, t, x=1.0 * (t - 200.0)), t)
        bus4.inject(compat.encode_state(_state(1, t, x=-15.0 + 1.0 * (t - 200.0)), ORIGIN))
        for r in me.poll(t + 0.02):
            sources.add(r.source)
            assert member.receive(r.state, t + 0.02)
    assert sources == {"j2735", "compat"}
    assert member.msgs_received == 40
    lead, mid = member.buffer.latest(0), member.buffer.latest(1)
    assert lead.x == pytest.approx(1.9, abs=6e-3) and lead.t == pytest.approx(201.9, abs=1e-3)
    assert mid.x == pytest.approx(-13.1, abs=1e-6) and mid.t == pytest.approx(201.9)
    assert lead.speed == pytest.approx(1.0) and mid.speed == pytest.approx(1.0)
    assert lead.heading == pytest.approx(0.1, abs=2e-4) and mid.heading == pytest.approx(0.1)


def test_clock_ahead_never_gives_negative_age():
    bus = MemoryBus()
    a, b = _link(bus, 0), _link(bus, 1)
    a.send(_state(0, 100.3), 100.3)  # sender's clock 0.3 s ahead of ours
    (r,) = b.poll(100.0)
    assert r.age == 0.0 and r.state.t == 100.0


def _mutations(rng: random.Random, frame: bytes) -> bytes:
    data = bytearray(frame)
    kind = rng.randrange(6)
    if kind == 0:  # flip 1..8 random bits
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(data) * 8)
            data[i // 8] ^= 0x80 >> (i % 8)
    elif kind == 1:  # truncate
        del data[rng.randrange(len(data)) :]
    elif kind == 2:  # extend with garbage
        data += rng.randbytes(rng.randint(1, 40))
    elif kind == 3:  # overwrite a random run of bytes
        i = rng.randrange(len(data))
        n = rng.randint(1, 8)
        data[i : i + n] = rng.randbytes(n)
    elif kind == 4:  # corrupt the open-type length octet
        data[2] = rng.randrange(256)
    else:  # insert or delete bytes in the middle
        i = rng.randrange(len(data))
        if rng.random() < 0.5:
            data[i:i] = rng.randbytes(rng.randint(1, 4))
        else:
            del data[i : i + rng.randint(1, 4)]
    return bytes(data)


def test_fuzz_receiver_never_raises_and_counts_every_datagram():
    rng = random.Random(2026)
    ids = TempIds("fuzz", 4)
    counters = Counters()
    rx = Receiver(
        ids, ORIGIN, 0, loss=LossConfig(per=0.2), rng=np.random.default_rng(3), counters=counters
    )
    unexpected = []
    real_malformed = rx._malformed

    def spy(source, why):  # count drops that came through the catch-all, i.e. our bugs
        if why.startswith("unexpected"):
            unexpected.append(why)
        return real_malformed(source, why)

    rx._malformed = spy
    vectors = [bytes.fromhex(v["hex"]) for v in load_vectors()]
    ours = [
        j.encode_frame(state_to_core(_state(i, 1e9 + k), ORIGIN, ids.id_of(i), k))
        for i in range(4)
        for k in range(10)
    ]
    ours += [compat.encode_state(_state(i, 1e9), ORIGIN) for i in range(4)]
    ours.append(compat.make_abort(1e9))
    valid = vectors + ours
    n = 100_000
    delivered = 0
    for k in range(n):
        r = rng.random()
        if r < 0.15:
            data = rng.randbytes(rng.randint(0, 300))
        elif r < 0.30:
            data = b"\x00\x14" + rng.randbytes(rng.randint(0, 120))
        elif r < 0.35:
            data = b"{" + rng.randbytes(rng.randint(0, 200))
        elif r < 0.40:
            data = rng.choice(valid)
        else:
            data = _mutations(rng, rng.choice(valid))
        got = rx.handle(data, 1e9 + 5.0 + k * 1e-4)
        if got is not None:
            delivered += 1
            assert got.state is None or got.state.t <= got.t_rx
    c = counters
    assert c.datagrams == n
    assert c.replays > 0  # the fuzz repeats valid frames verbatim: replays, not delivered twice
    assert c.received + c.malformed + c.filtered + c.echoes + c.duplicates + c.lost + c.replays == n
    assert c.received == delivered
    # every category was exercised
    assert min(c.received, c.malformed, c.filtered, c.echoes, c.lost) > 100
    assert unexpected == []
    # and the spy does see the catch-all: something that is not even bytes
    assert rx.handle(None, 0.0) is None  # type: ignore[arg-type]
    assert len(unexpected) == 1


def test_receiver_survives_pathological_values():
    rx = Receiver(IDS, ORIGIN, 0)
    # a member BSM at the pole with every field at its extreme
    core = j.BsmCore(
        msg_cnt=127, temp_id=IDS.id_of(1), sec_mark=60999, lat=j.LAT_MAX, lon=j.LON_MAX,
        elev=j.ELEV_MAX, speed=j.SPEED_MAX, heading=j.HEADING_MAX, yaw_rate=j.YAW_RATE_MIN,
        accel_long=j.ACCEL_MIN, width=j.WIDTH_MAX, length=j.LENGTH_MAX,
    )  # fmt: skip
    # secMark 60999 is the leap second :60.999; our clock (POSIX, no leap seconds) reads
    # it in the next minute, and it is rebuilt as the last instant of its minute, :59.999
    r = rx.handle(j.encode_frame(core), 60.5)
    assert r is not None and r.state.t == pytest.approx(59.999)
    assert r.state.speed == pytest.approx(163.8) and r.state.accel == pytest.approx(-20.0)
    assert r.state.yaw_rate == pytest.approx(math.radians(327.67))


@pytest.mark.parametrize(
    "field,value,what",
    [
        ("lat", j.LAT_UNAVAILABLE, "position"),
        ("lon", j.LON_UNAVAILABLE, "position"),
        ("speed", j.SPEED_UNAVAILABLE, "speed"),
        ("heading", j.HEADING_UNAVAILABLE, "heading"),
        ("sec_mark", j.SEC_MARK_UNAVAILABLE, "time"),
    ],
)
def test_member_bsm_without_essentials_is_not_delivered(field, value, what, caplog):
    rx = Receiver(IDS, ORIGIN, 0)
    base = state_to_core(_state(1, 10.0), ORIGIN, IDS.id_of(1), 0)
    with caplog.at_level("DEBUG", logger="openconvoy.comms.v2v"):
        assert rx.handle(j.encode_frame(base._replace(**{field: value})), 10.1) is None
    assert rx.counters.malformed == 1 and rx.counters.received == 0
    assert f"BSM of vehicle 1 lacks {what}" in caplog.text
    assert rx.handle(j.encode_frame(base), 10.1) is not None  # the intact one is fine


def test_receive_errors_do_not_stop_the_link():
    class Broken:
        def recv_all(self, max_batch=10_000):
            raise OSError(100, "Network is down")

        def send(self, data):
            raise OSError(100, "Network is down")

        def close(self):
            pass

    link = V2V(LinkConfig(iface="x"), IDS, ORIGIN, 0, transport=Broken())
    assert link.poll(1.0) == [] and link.counters.recv_errors == 1
    assert link.send(_state(0, 1.0), 1.0) is False and link.counters.send_errors == 1
    assert link.counters.sent == 0


def test_sender_counts_into_shared_counters():
    c = Counters()
    s = Sender(IDS, ORIGIN, 1, counters=c, compat_enabled=True)
    frame, twin = s.datagrams(_state(1, 3.0), 3.0)
    assert frame[:2] == b"\x00\x14" and compat.decode(twin).car == 1


def test_compat_twins_do_not_undo_emulated_loss():
    bus, bus4 = MemoryBus(), MemoryBus()
    tx = _link(bus, 0, bus4)
    rx = _link(bus, 1, bus4, loss=LossConfig(per=0.5), rng=np.random.default_rng(4))
    for k in range(1000):
        t = 0.1 * k
        tx.send(_state(0, t), t)
        rx.poll(t + 0.01)
    c = rx.counters
    # every twin is a duplicate; the J2735 copies alone meet the loss model
    assert c.duplicates == 1000 and c.received + c.lost == 1000
    assert abs(c.received / 1000 - 0.5) < 2.576 * (0.25 / 1000) ** 0.5


def test_link_config_from_the_convoy_config():
    from openconvoy.convoy import V2VConfig

    cfg = LinkConfig.from_v2v(
        V2VConfig(group="ff15::1234", port=4300, compat=True, auth="off"), "wlan0"
    )
    assert (cfg.iface, cfg.group, cfg.port, cfg.hop_limit, cfg.compat) == (
        "wlan0", "ff15::1234", 4300, 1, True
    )  # fmt: skip
    assert (cfg.compat_group, cfg.compat_port, cfg.compat_ttl) == ("224.0.0.1", 5004, 1)
    # the convoy config's defaults are the transport's
    assert LinkConfig.from_v2v(V2VConfig(), "x") == LinkConfig("x")


def _foreign_frames(n: int, temp_id: bytes = b"\xde\xad\xbe\xef") -> list[bytes]:
    frames = [
        j.encode_frame(state_to_core(_state(0, 10.0), ORIGIN, temp_id, k)) for k in range(128)
    ]
    return [frames[k % 128] for k in range(n)]


@given(
    cnt=st.integers(0, 127),
    temp_id=st.binary(min_size=4, max_size=4),
    speed=st.integers(0, 8191),
    part_ii=st.none() | st.integers(0, 300),
)
@settings(max_examples=60, deadline=None)
def test_peek_temp_id_reads_the_id_asn1tools_encoded(cnt, temp_id, speed, part_ii):
    # with and without Part II, whose size moves the BSM behind a 1- or 2-octet length
    core = j.BsmCore(cnt, temp_id, 1000, 286024000, -812001000, speed=speed)
    frame_t, bsm_t = j._spec()
    value = {"coreData": j._to_asn(core)["coreData"]}
    if part_ii is not None:
        value["partII"] = [{"partII-Id": 0, "partII-Value": bytes(part_ii)}]
    frame = frame_t.encode({"messageId": 20, "value": bsm_t.encode(value)})
    assert j.peek_temp_id(frame) == int.from_bytes(temp_id, "big")
    assert j.decode_frame(frame).core.temp_id == temp_id


def test_peek_temp_id_of_non_frames_is_none():
    assert j.peek_temp_id(b"") is None and j.peek_temp_id(b"\x00\x14") is None
    assert j.peek_temp_id(b"\x00\x14\x05\x01") is None  # too short for an id
    assert j.peek_temp_id(b'{"car": 1}') is None and j.peek_temp_id(b"\x00\x13" + bytes(20)) is None


def test_foreign_bsms_are_dropped_without_a_full_decode(monkeypatch):
    rx = Receiver(IDS, ORIGIN, 1)
    member = j.encode_frame(state_to_core(_state(0, 10.0), ORIGIN, IDS.id_of(0), 3))
    calls = []
    real = j.decode_frame
    monkeypatch.setattr(j, "decode_frame", lambda data: calls.append(1) or real(data))
    for frame in _foreign_frames(500):
        assert rx.handle(frame, 10.05) is None
    assert rx.handle(member, 10.05) is not None
    assert calls == [1]  # only the member's frame was decoded
    assert rx.counters.filtered == 500 and rx.counters.received == 1 and _balanced(rx.counters)


class TickClock:
    """A monotonic clock that advances ``step`` seconds each time it is read."""

    def __init__(self, step: float) -> None:
        self.t, self.step = 0.0, step

    def __call__(self) -> float:
        self.t += self.step
        return self.t


def test_poll_is_bounded_by_its_time_budget_and_the_rest_waits():
    # 40,000 foreign BSMs waiting (a second of the flood that stalled deploys), read with
    # a clock that advances 1 ms per reading: a 12.5 ms budget stops the poll after a few
    # chunks; later polls go on where it stopped, and nothing is lost or counted twice.
    bus = MemoryBus()
    link = _link(bus, 1, clock=TickClock(0.001))
    bus.inject_many(_foreign_frames(40_000))
    assert link.poll(10.0, budget_s=0.0125) == []
    first = link.counters.datagrams
    assert 0 < first <= 14 * POLL_CHUNK and link.counters.budget_hits == 1
    polls, most = 1, first
    while link.counters.datagrams < 40_000:
        before = link.counters.datagrams
        link.poll(10.0, budget_s=0.0125)
        most = max(most, link.counters.datagrams - before)
        polls += 1
    assert link.counters.filtered == 40_000 and _balanced(link.counters)
    assert most <= 14 * POLL_CHUNK and polls >= math.ceil(40_000 / most)
    assert link.counters.budget_hits in (polls - 1, polls)
    # without a budget, one poll reads everything (the old behaviour, for tools)
    bus.inject_many(_foreign_frames(1000))
    link.poll(10.0)
    assert link.counters.datagrams == 41_000


def test_poll_with_a_budget_takes_turns_between_the_two_sockets():
    bus, bus4 = MemoryBus(), MemoryBus()
    link = _link(bus, 1, bus4=bus4, clock=TickClock(0.001))
    bus.inject_many(_foreign_frames(10_000))
    leader = _link(bus, 0, bus4=bus4)
    leader.send(_state(0, 10.0), 10.0)  # a J2735 BSM behind the flood, and its compat twin
    got = link.poll(10.01, budget_s=0.005)
    assert [(r.source, r.sender) for r in got] == [("compat", 0)]  # heard despite the flood


def test_unavailable_heading_keeps_position_and_speed_and_takes_a_known_heading():
    rx = Receiver(IDS, ORIGIN, 0)
    blind = dict(heading=j.HEADING_UNAVAILABLE)
    core = lambda s: state_to_core(s, ORIGIN, IDS.id_of(1), 0)  # noqa: E731
    # nothing known yet: not delivered (a made-up heading would steer the followers)
    assert rx.handle(j.encode_frame(core(_state(1, 10.0))._replace(**blind)), 10.1) is None
    assert rx.counters.malformed == 1
    moving = replace(_state(1, 10.0), heading=0.3, speed=0.0)
    assert rx.handle(j.encode_frame(core(moving)), 10.1).state.heading == pytest.approx(
        0.3, abs=1e-3
    )
    # standing still, heading unavailable: the last heading it sent
    r = rx.handle(j.encode_frame(core(replace(moving, t=10.2))._replace(**blind)), 10.25)
    assert r is not None and r.state.heading == pytest.approx(0.3, abs=1e-3)
    assert (r.state.x, r.state.y, r.state.speed) == pytest.approx(
        (moving.x, moving.y, 0.0), abs=0.02
    )
    # it moved 2 m north (heading still unavailable): the direction of its trail
    north = replace(moving, t=10.3, y=moving.y + 2.0, speed=1.0)
    r = rx.handle(j.encode_frame(core(north)._replace(**blind)), 10.35)
    assert r.state.heading == pytest.approx(math.pi / 2, abs=0.02)
    assert r.state.speed == pytest.approx(1.0) and r.state.y == pytest.approx(north.y, abs=0.02)


def test_interop_frames_with_unavailable_heading_are_delivered_once_a_heading_is_known():
    blind = [
        bytes.fromhex(v["hex"])
        for v in load_vectors()
        if v["decoded_core_fields"]["heading"] == j.HEADING_UNAVAILABLE
    ]
    assert len(blind) == 8
    delivered = 0
    for data in blind:
        c = j.decode_frame(data).core
        ids = TempIds("x", 2, {1: c.temp_id.hex()})
        rx = Receiver(ids, ORIGIN, 0, time_tolerance_s=120.0)
        t_rx = 600.0 + c.sec_mark / 1000 if c.sec_mark < 60000 else 600.0
        if c.lat == j.LAT_UNAVAILABLE or c.speed == j.SPEED_UNAVAILABLE or c.sec_mark >= 61000:
            assert rx.handle(data, t_rx) is None  # lacks more than the heading
            continue
        seen = j.encode_frame(c._replace(heading=0))  # one earlier frame that had a heading
        assert rx.handle(seen, t_rx) is not None
        r = rx.handle(data, t_rx)
        assert r is not None and r.state.speed == pytest.approx(c.speed * j.SPEED_UNIT)
        assert r.state.heading == pytest.approx(math.pi / 2)  # compass 0 = ENU north
        delivered += 1
    assert delivered == 6  # the other two lack speed as well
