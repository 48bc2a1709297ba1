"""Signature verification under a keyless flood (issue 22, D52): what a follower can verify,
what a wrongly signed frame costs it, and how old the leader's newest BSM is when a flood
of wrongly signed copies of the leader's BSMs arrives at several rates.

Real parts: real ECDSA P-256 (``cryptography``), real IEEE 1609.2 SPDUs, the follower's real
``V2V.poll`` with the deploy loop's receive budget (0.4 of a 20 Hz period) timed by the real
clock; the transport is the in-memory bus (``comms.multicast.MemoryBus``), so the figures
are the receiver's, not the kernel's. Prints one JSON object::

    python benchmarks/bench_verify_flood.py [--seconds 3] [--rates 0,5000,15000,30000]

Quote ``uptime``'s load average beside the figures: the machine's other work moves them.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import tempfile
import time
from pathlib import Path

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("bench", 3)
RATE_HZ = 20.0
BUDGET_S = 0.4 / RATE_HZ
#: The V2V socket buffer in datagrams (256 KiB doubled by Linux, ~1 KiB per small datagram).
SOCKET_DATAGRAMS = 512


def _state(i: int, t: float, t0: float) -> VehicleState:
    return VehicleState(i, t, 2.0 * (t - t0) - 15.0 * i, 0.0, 2.0, 0.0, 0.0, 0.0, 0.8, 0.3)


def _keys(now: float) -> Path:
    d = Path(tempfile.mkdtemp(prefix="oc-bench-")) / "bench.keys"
    ks.init_authority(d, "bench", now)
    for i in range(3):
        ks.issue_vehicle(d, "bench", i, now)
    return d


class _Forger:
    def __init__(self, captured: bytes) -> None:
        self._at = captured.index(sp.decode_signed(captured).generation_time.to_bytes(8, "big"))
        self._f = bytearray(captured)
        self._rng = random.Random(1)

    def frame(self, t: float) -> bytes:
        self._f[self._at : self._at + 8] = c.time64(t).to_bytes(8, "big")
        self._f[-32:] = self._rng.randbytes(32)
        return bytes(self._f)


def _links(keys: Path, t0: float) -> tuple[MemoryBus, V2V, V2V]:
    bus = MemoryBus()
    leader = V2V(LinkConfig("mem"), IDS, ORIGIN, 0, transport=bus.endpoint("v0"),
                 auth=Authenticator(ks.load_vehicle(keys, 0, t0)))  # fmt: skip
    follower = V2V(LinkConfig("mem"), IDS, ORIGIN, 1, transport=bus.endpoint("v1", capacity=SOCKET_DATAGRAMS),
                   auth=Authenticator(ks.load_vehicle(keys, 1, t0)), clock=time.perf_counter)  # fmt: skip
    leader.send(_state(0, t0, t0), t0)  # with its certificate
    follower.poll(t0 + 0.01)
    return bus, leader, follower


def verify_rate(keys: Path, t0: float, n: int = 400) -> float:
    """Genuine BSM verifications a second (``Authenticator.check``)."""
    signer = Authenticator(ks.load_vehicle(keys, 0, t0))
    a = Authenticator(ks.load_vehicle(keys, 1, t0))
    spdus = [
        sp.decode_signed(signer.sign(b"\x00\x14" + bytes(30), c.PSID_BSM, t0 + k * 1e-3))
        for k in range(n)
    ]
    start = time.perf_counter()
    for k, s in enumerate(spdus):
        assert not isinstance(a.check(s, t0 + k * 1e-3), str)
    return n / (time.perf_counter() - start)


def flood(keys: Path, t0: float, rate: int, seconds: float) -> dict:
    """The leader's BSM age at every tick of a flood at ``rate`` a second, and the cost."""
    bus, leader, follower = _links(keys, t0)
    sent = leader.sender.datagrams(_state(0, t0 + 0.03, t0), t0 + 0.03)
    assert sent is not None
    forger = _Forger(sent[0])
    per_tick = int(rate / RATE_HZ)
    pick = random.Random(7)
    last_t, ages, poll_s = t0, [], []
    for k in range(2, 2 + int(seconds * RATE_HZ)):
        t = t0 + k / RATE_HZ
        frames = [forger.frame(t - 0.02 + i * 1e-6) for i in range(per_tick)]
        # the genuine frame at a random place among the period's flood (it arrives when
        # it arrives; the socket buffer keeps the first SOCKET_DATAGRAMS)
        at = pick.randint(0, per_tick)
        bus.inject_many(frames[:at], "attacker")
        leader.send(_state(0, t - 0.005, t0), t - 0.005)
        bus.inject_many(frames[at:], "attacker")
        start = time.perf_counter()
        for m in follower.poll(t, budget_s=BUDGET_S):
            if m.state is not None and m.sender == 0:
                last_t = max(last_t, m.state.t)
        poll_s.append(time.perf_counter() - start)
        ages.append(t - last_t)
    ages.sort()
    poll_s.sort()
    c_ = follower.counters
    return {
        "flood_per_s": rate,
        "leader_age_max_s": round(ages[-1], 4),
        "leader_age_p95_s": round(ages[int(0.95 * (len(ages) - 1))], 4),
        "poll_ms_p50": round(1e3 * poll_s[len(poll_s) // 2], 2),
        "poll_ms_max": round(1e3 * poll_s[-1], 2),
        "budget_ms": round(1e3 * BUDGET_S, 1),
        "shed": c_.shed,
        "dropped_by_full_buffer": bus.dropped,
        "bad_signatures": follower.auth.counters.rejected["bad_signature"] if follower.auth else 0,
        "us_per_flood_frame": round(1e6 * sum(poll_s) / max(1, per_tick * len(poll_s)), 2),
        "alerts": follower.take_alerts()[:1],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rates", default="0,5000,15000,30000")
    args = ap.parse_args()
    t0 = time.time()
    keys = _keys(t0)
    out = {
        "load_average": os.getloadavg(),
        "verifications_per_s": round(verify_rate(keys, t0)),
        "floods": [flood(keys, t0, int(r), args.seconds) for r in args.rates.split(",")],
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
