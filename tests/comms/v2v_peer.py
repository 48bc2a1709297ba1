"""One convoy member for the network-namespace tests: send at RATE Hz, poll, report JSON.

Usage: v2v_peer.py INDEX N_VEHICLES BARRIER_DIR DURATION_S RATE_HZ PER SEED DROP_AT [MODE]

MODE is ``j2735`` (default), ``legacy_json`` (J2735 plus the compatibility twin on IPv4) or
``legacy`` (a vehicle running the original implementation: compatibility JSON on IPv4
only). Peers first meet at a barrier (a ready file each in BARRIER_DIR, written once
their sockets are joined), then all start at the same instant.

Vehicle i drives east along y = 0 from x = -15 i at 1 m/s from the start, so a receiver
can check every state it gets against where the sender really was at the message's
(reconstructed) send time.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.loss import LossConfig
from openconvoy.comms.multicast import Ipv4Multicast
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig, Received
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
SPEED = 1.0


def true_x(index: int, t: float, start_at: float) -> float:
    return -15.0 * index + SPEED * (t - start_at)


class LegacyLink:
    """The original implementation, as far as the wire shows: JSON on IPv4 only."""

    def __init__(self, iface: str, index: int) -> None:
        self.sock, self.index = Ipv4Multicast(iface), index
        self.counters = type("C", (), {})()
        self.counters.sent = 0
        self.metadata = {"legacy": True}

    def send(self, state: VehicleState, now: float) -> bool:
        self.sock.send(cj.encode_state(state, ORIGIN))
        self.counters.sent += 1
        return True

    def poll(self, now: float, budget_s: float | None = None) -> list[Received]:
        out = []
        for d in self.sock.recv_all():
            try:
                m = cj.decode(d.data)
            except cj.CompatDecodeError:
                continue
            if m.car != self.index:
                out.append(Received(cj.to_state(m, ORIGIN), now, m.abort, "compat", m.car))
        return out

    def close(self) -> None:
        self.sock.close()


def barrier(directory: Path, name: str, index: int, n: int, while_waiting=lambda: None) -> float:
    """Announce ``name`` for this peer, wait for all n; the latest announcement time."""
    tmp = directory / f".{name}.{index}"
    tmp.write_text(str(time.time()))
    tmp.rename(directory / f"{name}.{index}")  # atomic: readers never see a partial file
    deadline = time.monotonic() + 60.0
    while True:
        stamps = [directory / f"{name}.{i}" for i in range(n)]
        if all(p.exists() for p in stamps):
            return max(float(p.read_text()) for p in stamps)
        if time.monotonic() > deadline:
            raise SystemExit(f"barrier {name}: the other peers never arrived")
        while_waiting()
        time.sleep(0.005)


def main() -> int:
    index, n = int(sys.argv[1]), int(sys.argv[2])
    barrier_dir, duration, rate = Path(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
    per, seed, drop_at = float(sys.argv[6]), int(sys.argv[7]), sys.argv[8]
    mode = sys.argv[9] if len(sys.argv) > 9 else "j2735"
    iface = os.environ["OPENCONVOY_NETNS_IFACE"]
    if mode == "legacy":
        link = LegacyLink(iface, index)
    else:
        link = V2V(
            LinkConfig(iface=iface, compat=mode == "compat"),
            TempIds("netns-test", n),
            ORIGIN,
            index,
            loss=LossConfig(per=per) if per > 0 else None,
            drop_at=drop_at,
            rng=np.random.default_rng(seed),
        )
    # Everyone has joined the group before anyone sends: a common start after the last.
    start_at = math.ceil(barrier(barrier_dir, "ready", index, n) * 10.0) / 10.0 + 1.0
    heard = {j: 0 for j in range(n) if j != index}
    by_source: dict[str, int] = {}
    max_pos_err, min_age, max_age = 0.0, float("inf"), 0.0
    attempts = 0

    def poll() -> None:
        nonlocal max_pos_err, min_age, max_age
        now = time.time()
        for r in link.poll(now):
            heard[r.sender] += 1
            by_source[r.source] = by_source.get(r.source, 0) + 1
            err = abs(r.state.x - true_x(r.sender, r.state.t, start_at)) + abs(r.state.y)
            max_pos_err = max(max_pos_err, err)
            min_age, max_age = min(min_age, r.age), max(max_age, r.age)

    late = max(0.0, time.time() - start_at)
    while time.time() < start_at:
        time.sleep(0.005)
    period = 1.0 / rate
    for k in range(round(duration * rate)):
        target = start_at + k * period
        while (now := time.time()) < target:
            poll()
            time.sleep(min(0.005, max(0.0, target - now)))
        state = VehicleState(index, now, true_x(index, now, start_at), 0.0, SPEED, 0.0)
        link.send(state, now)
        attempts += 1
        poll()
    # Keep listening until every peer has sent its last message, then a little more.
    barrier(barrier_dir, "done", index, n, while_waiting=poll)
    end = time.time() + 0.3
    while time.time() < end:
        poll()
        time.sleep(0.005)
    c = link.counters
    print(
        json.dumps(
            {
                "index": index,
                "attempts": attempts,
                "heard": heard,
                "counters": c.__dict__,
                "max_pos_err_m": max_pos_err,
                "min_age_s": min_age,
                "max_age_s": max_age,
                "by_source": by_source,
                "late_start_s": late,
                "metadata": link.metadata,
            }
        )
    )
    link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
