"""One convoy member for the network-namespace tests: send at RATE Hz, poll, report JSON.

Usage: v2v_peer.py INDEX N_VEHICLES START_AT DURATION_S RATE_HZ PER SEED DROP_AT [compat]

Vehicle i drives east along y = 0 from x = -15 i at 1 m/s from START_AT (Unix time), so a
receiver can check every state it gets against where the sender really was at the
message's (reconstructed) send time.
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.loss import LossConfig
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
SPEED = 1.0


def true_x(index: int, t: float, start_at: float) -> float:
    return -15.0 * index + SPEED * (t - start_at)


def main() -> int:
    index, n = int(sys.argv[1]), int(sys.argv[2])
    start_at, duration, rate = float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
    per, seed, drop_at = float(sys.argv[6]), int(sys.argv[7]), sys.argv[8]
    compat = len(sys.argv) > 9 and sys.argv[9] == "compat"
    iface = os.environ["OPENCONVOY_NETNS_IFACE"]
    link = V2V(
        LinkConfig(iface=iface, compat=compat),
        TempIds("netns-test", n),
        ORIGIN,
        index,
        loss=LossConfig(per=per) if per > 0 else None,
        drop_at=drop_at,
        rng=np.random.default_rng(seed),
    )
    heard = {j: 0 for j in range(n) if j != index}
    max_pos_err, min_age, max_age, sources = 0.0, float("inf"), 0.0, set()
    attempts = 0

    def poll() -> None:
        nonlocal max_pos_err, min_age, max_age
        now = time.time()
        for r in link.poll(now):
            heard[r.sender] += 1
            sources.add(r.source)
            err = abs(r.state.x - true_x(r.sender, r.state.t, start_at)) + abs(r.state.y)
            max_pos_err = max(max_pos_err, err)
            min_age, max_age = min(min_age, r.age), max(max_age, r.age)

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
    end = time.time() + 0.5  # let the last messages of the others arrive
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
                "sources": sorted(sources),
                "metadata": link.metadata,
            }
        )
    )
    link.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
