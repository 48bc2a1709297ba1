"""Inside a private network namespace (``comms.netns``): a signed leader and a follower
(real ``V2V`` links, real IPv6 multicast sockets with the vehicle's socket buffer), and a
flood process sending wrongly signed copies of the leader's BSMs at ``RATE`` a second.
The follower polls at 20 Hz with the deploy loop's receive budget and records, every
tick, how old the newest leader BSM it has is. Prints one JSON object.

Usage: python flood_netns_driver.py KEYS_DIR RATE SECONDS
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)
RATE_HZ = 20.0

FLOODER = """
import random, sys, time
sys.path.insert(0, sys.argv[4])
from flood_testdata import Forger
from openconvoy.comms.multicast import Ipv6Multicast
captured, rate, seconds = bytes.fromhex(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
forger, sock = Forger(captured, seed=3), Ipv6Multicast(sys.argv[5], "ff15::4f43", 4200, 1)
t0, n = time.time(), 0
while time.time() - t0 < seconds:
    due = int((time.time() - t0) * rate)
    while n < due:
        sock.send(forger.frame(time.time() - 0.01 + n * 1e-7))
        n += 1
    time.sleep(0.001)
print(n)
"""


def _state(t: float, t0: float) -> VehicleState:
    return VehicleState(0, t, 2.0 * (t - t0), 0.0, 2.0, 0.0, 0.0, 0.0, 0.8, 0.3)


def main() -> None:
    keys, rate, seconds = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
    iface = os.environ["OPENCONVOY_NETNS_IFACE"]
    now = time.time()
    leader = V2V(
        LinkConfig(iface), IDS, ORIGIN, 0, auth=Authenticator(ks.load_vehicle(keys, 0, now))
    )
    follower = V2V(
        LinkConfig(iface), IDS, ORIGIN, 1, auth=Authenticator(ks.load_vehicle(keys, 1, now))
    )
    t0 = time.time()
    leader.send(_state(t0, t0), t0)  # with its certificate
    time.sleep(0.02)
    follower.poll(time.time())
    sent = leader.sender.datagrams(_state(t0 + 0.01, t0), t0 + 0.01)
    assert sent is not None
    flooder = subprocess.Popen(
        [sys.executable, "-c", FLOODER, sent[0].hex(), str(rate), str(seconds),
         str(Path(__file__).parent), iface],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    ages, last_t, k = [], t0, 0
    end = time.monotonic() + seconds + 1.0
    next_tick = time.monotonic()
    while time.monotonic() < end:
        next_tick += 1.0 / RATE_HZ
        time.sleep(max(0.0, next_tick - time.monotonic()))
        t = time.time()
        leader.send(_state(t, t0), t)
        for m in follower.poll(t, budget_s=0.4 / RATE_HZ):
            if m.state is not None and m.sender == 0:
                last_t = max(last_t, m.state.t)
        k += 1
        if k > RATE_HZ * 0.5:  # the flood is on
            ages.append(t - last_t)
    out, _ = flooder.communicate(timeout=30)
    c = follower.counters
    print(
        json.dumps(
            {
                "flood_sent": int(out.strip() or 0),
                "ages": ages,
                "shed": c.shed,
                "bad_signatures": follower.auth.counters.rejected["bad_signature"],
                "datagrams": c.datagrams,
                "alerts": follower.take_alerts(),
                "load_average": os.getloadavg(),
            }
        )
    )


if __name__ == "__main__":
    main()
