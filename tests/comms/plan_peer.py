"""Inside a private network namespace: vehicle 1 sends signed BSMs and plans over IPv6
multicast, vehicle 2 receives them through its verifying V2V link, and a bare socket on
the same group (what a foreign stack sees) records every datagram. Prints JSON.

Usage: plan_peer.py KEYS_DIR ROUNDS
"""

from __future__ import annotations

import json
import os
import sys
import time

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import Ipv6Multicast
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.plans import Plan
from openconvoy.core.state import VehicleState


def main() -> int:
    keys, rounds = sys.argv[1], int(sys.argv[2])
    iface = os.environ["OPENCONVOY_NETNS_IFACE"]
    ids, origin, now = TempIds("lab", 3), Origin(28.6024, -81.2001, 0.0), time.time()
    cfg = LinkConfig(iface=iface)
    tx = V2V(cfg, ids, origin, 1, auth=Authenticator(ks.load_vehicle(keys, 1, now)))
    rx = V2V(cfg, ids, origin, 2, auth=Authenticator(ks.load_vehicle(keys, 2, now)))
    tap = Ipv6Multicast(iface)
    time.sleep(0.2)
    plans, states, raw = [], [], []
    for k in range(rounds):
        t = time.time()
        tx.send(VehicleState(1, t, -15.0 + 0.1 * k, 0.0, 2.0, 0.0), t)
        speeds = tuple(2.0 + 0.1 * j for j in range(21))
        tx.send_plan(Plan(1, t + 0.1, 0.1, speeds, 0.3), t)
        time.sleep(0.05)
        for r in rx.poll(time.time()):
            if r.plan is not None:
                plans.append({"sender": r.sender, "t0": r.plan.t0, "speeds": list(r.plan.speeds)})
            elif r.state is not None:
                states.append({"sender": r.sender, "speed": r.state.speed})
        raw += [d.data.hex() for d in tap.recv_all()]
    c = rx.counters
    print(json.dumps({"plans": plans, "states": states, "raw": raw,
                      "counters": {"received": c.received, "plans": c.plans,
                                   "rejected": c.rejected, "malformed": c.malformed}}))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
