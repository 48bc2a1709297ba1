"""D52: a keyless flood of wrongly signed BSMs claiming the leader, at 15,000 a second, through
a follower's real ``V2V.poll`` (MemoryBus transport, the real clock timing its 20 ms receive
budget, real ECDSA): the leader's genuine BSMs keep arriving every tick and the operator is
told. benchmarks/bench_verify_flood.py prints the throughput figures."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
from auth_testdata import T0, creds, keys_dir
from flood_testdata import Forger

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.netns import netns_unavailable_reason, run_in_netns
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig, _Pending, schedule
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)
RATE_HZ = 20.0
BUDGET_S = 0.4 / RATE_HZ  # bridge.exchange.RECEIVE_BUDGET of a 20 Hz loop
FLOOD_PER_TICK = 750  # 15,000 a second
#: What the V2V socket buffer holds (multicast.V2V_RCVBUF_BYTES, 256 KiB, which Linux
#: doubles, over the ~1 KiB the kernel accounts a small datagram): beyond, it drops.
SOCKET_DATAGRAMS = 512


def _state(i: int, t: float) -> VehicleState:
    return VehicleState(i, t, 2.0 * (t - T0) - 15.0 * i, 0.0, 2.0, 0.0, 0.0, 0.0, 0.8, 0.3)


def test_genuine_bsms_keep_a_bounded_age_under_a_wrongly_signed_flood():
    bus = MemoryBus()
    leader = V2V(
        LinkConfig("mem"), IDS, ORIGIN, 0, transport=bus.endpoint("0"), auth=Authenticator(creds(0))
    )
    follower = V2V(
        LinkConfig("mem"),
        IDS,
        ORIGIN,
        1,
        transport=bus.endpoint("1", capacity=SOCKET_DATAGRAMS),
        auth=Authenticator(creds(1)),
        clock=time.perf_counter,
    )
    # the attacker captured one of the leader's digest-signed BSMs
    leader.send(_state(0, T0), T0)  # (with its certificate)
    (r,) = follower.poll(T0 + 0.01)
    forger = Forger(_last_sent(leader, T0 + 0.03))
    ages, last_t = [], r.state.t
    for k in range(2, 82):  # 4 s; the flood starts after a second of normal traffic
        t = T0 + k / RATE_HZ
        flood = [forger.frame(t - 0.02 + i * 1e-6) for i in range(FLOOD_PER_TICK)]
        if k >= 22:  # the leader's BSM arrives amid the flood, not first
            bus.inject_many(flood[:200], "attacker")
        leader.send(_state(0, t - 0.005), t - 0.005)
        if k >= 22:
            bus.inject_many(flood[200:], "attacker")
        for m in follower.poll(t, budget_s=BUDGET_S):
            if m.state is not None and m.sender == 0:
                last_t = max(last_t, m.state.t)
        if k >= 22:
            ages.append(t - last_t)
    c = follower.counters
    bad = follower.auth.counters.rejected["bad_signature"]
    print(f"flood: ages max {max(ages):.3f} s, shed {c.shed}, bad signatures {bad}")
    # the leader's newest BSM (5 ms old when read) nearly every tick, never 3 ticks late
    # (D52: it was up to 2 s, and a follower latched "stale")
    assert sorted(ages)[len(ages) // 2] < 0.01 and max(ages) < 3.2 / RATE_HZ, ages
    # the flood cost little: beyond what the socket holds it was dropped, of the rest a few
    # were verified a tick (per claimed sender), the others shed unverified
    assert c.shed + bad + bus.dropped >= 60 * FLOOD_PER_TICK - 5 and c.shed > 0
    assert bad <= 60 * 4 + 60
    alerts = follower.take_alerts()
    assert any("V2V flood" in a and "claiming vehicle 0" in a and "attacker" in a for a in alerts)


def _last_sent(link: V2V, t: float) -> bytes:
    # a fresh digest-signed SPDU of the leader (the certificate went out in the first)
    frame = link.sender.datagrams(_state(0, t), t)
    assert frame is not None
    return frame[0]


def test_schedule_serves_the_usual_source_then_the_newest_and_every_sender_in_turn():
    from openconvoy.comms.security import spdu as sp

    def item(group, source, gen, cert=False):
        spdu = sp.SignedSpdu(0x20, gen, b"", b"d" * 8, b"c" if cert else None, None, b"", b"", b"")
        return _Pending(group, source, spdu, "bsm")

    flood = [item(0, "attacker", 100 + k) for k in range(50)]
    genuine = item(0, "v0", 90)
    other = item(2, "v2", 95)
    order, shed = schedule([*flood, genuine, other], {0: "v0", 2: "v2"}, per_sender=4)
    assert order[0] is genuine and order[1] is other  # each group's usual source first
    assert [p.spdu.generation_time for p in order[2:]] == [149, 148, 147]  # then the newest
    assert len(shed) == 47


@pytest.mark.netns
def test_a_real_flood_over_ipv6_multicast_leaves_the_leader_heard(tmp_path):
    """The same through real sockets in a private network namespace: 8,000 wrongly signed
    frames a second for 3 s, a real follower polling at 20 Hz with its receive budget."""
    reason = netns_unavailable_reason()
    assert reason is None, f"this test needs a private network namespace: {reason}"
    driver = Path(__file__).with_name("flood_netns_driver.py")
    (r,) = run_in_netns(
        [[sys.executable, str(driver), str(keys_dir("lab")), "8000", "3"]], timeout=60
    )
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    ages = sorted(res["ages"])
    print(
        {k: v for k, v in res.items() if k != "ages"},
        "median",
        ages[len(ages) // 2],
        "max",
        ages[-1],
    )
    assert res["flood_sent"] > 15_000, res["flood_sent"]
    assert res["bad_signatures"] + res["shed"] > 10_000
    # the leader's newest BSM: most ticks within a few periods, never near the 3 s
    # staleness backstop (D52: up to 2 s, and a follower latched "stale"). The kernel drops
    # what overflows the socket buffer between polls, genuine frames among them, and on a
    # busy 2-core machine the follower's ticks run late too.
    assert ages[int(0.8 * len(ages))] < 0.5 and ages[-1] < 2.0, ages
    assert any("V2V flood" in a and "claiming vehicle 0" in a for a in res["alerts"])
