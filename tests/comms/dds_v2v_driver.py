"""V2V over ROS 2 with a real rclpy node: run inside a private network namespace
(``unshare -rn``; ``test_dds.py`` starts it), prints one JSON line of what happened.

Two vehicles' ``V2V`` links of convoy ``lab`` (signed, IEEE 1609.2) over ``DdsTransport`` on
the namespace's veth ``oc0``; an rclpy node (``Ros2Node``, the rclpy wheels' Fast DDS) in the
same namespace subscribes to ``/openconvoy/v2v`` as ``openconvoy_msgs/msg/V2VBytes`` and hands
the bytes back; then that node publishes garbage and a replay of a frame it heard, as a
foreign ROS 2 node on the lab's domain could; last, ``openconvoy abort`` of a convoy file
with ``transport = "ros2"`` sends the authority's signed abort on the topic.

Usage (inside ``netns.run_in_netns``): python dds_v2v_driver.py KEYS_DIR
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from openconvoy.comms import netns
from openconvoy.comms.dds import DdsTransport
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)
GARBAGE = ([0x03, 0x81], [0xDE, 0xAD, 0xBE, 0xEF] * 20, [])


def main() -> int:
    keys = Path(sys.argv[1])
    iface = os.environ[netns.ENV_IFACE]
    # A lab's ROS 2 node finds its peers on the network: here the private namespace's.
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    from openconvoy.bridge.ros.ros2 import Ros2Node

    heard: list[dict] = []
    spy = Ros2Node("/v2v_spy")
    spy.subscribe("/openconvoy/v2v", "openconvoy_msgs/V2VBytes", heard.append)
    spy.advertise("/openconvoy/v2v", "openconvoy_msgs/V2VBytes")
    now = time.time()
    transports = [DdsTransport(iface, vehicle_id=i) for i in range(2)]
    links = [
        V2V(
            LinkConfig(iface),
            IDS,
            ORIGIN,
            i,
            transport=transports[i],
            auth=Authenticator(ks.load_vehicle(keys, i, now), window_s=1.0),
        )
        for i in range(2)
    ]
    got: list[dict] = []
    sent = 0
    t_end = time.monotonic() + 20.0
    while time.monotonic() < t_end and (len(heard) < 10 or len(got) < 10):
        t = time.time()
        links[0].send(VehicleState(0, t, 5.0 + 0.1 * sent, 2.0, 1.25, 0.5), t)
        sent += 1
        time.sleep(0.1)
        for r in links[1].poll(time.time()):
            got.append({"sender": r.sender, "x": r.state.x, "speed": r.state.speed})
    # A foreign node's garbage, and a replay of a genuine frame (after the receiver took it).
    replayed = bytes(heard[0]["data"]) if heard else b""
    for data in [*GARBAGE, list(replayed)]:
        spy.publish(
            "/openconvoy/v2v",
            {"header": {"stamp": time.time()}, "vehicle_id": 0, "direction": "tx", "data": data},
        )
    time.sleep(1.0)
    late = links[1].poll(time.time())
    rx = links[1]
    # `openconvoy abort` of a convoy whose V2V goes over ROS 2: signed by the authority, on
    # the convoy's topic; vehicle 1 obeys it.
    convoy = keys.parent / "lab.toml"
    convoy.write_text(
        '[convoy]\nname = "lab"\nvehicles = ["1/10", "1/10", "1/10"]\n'
        f'[v2v]\nkeys = "{keys}"\ntransport = "ros2"\n'
    )
    abort = subprocess.run(
        [sys.executable, "-m", "openconvoy.cli", "abort", "--iface", iface]
        + ["--convoy", str(convoy), "--key", str(keys / "authority.key")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    aborts = [r.sender for r in rx.poll(time.time()) if r.abort]
    out = {
        "sent": sent,
        "heard": [
            {k: m[k] for k in ("vehicle_id", "direction")} | {"data": bytes(m["data"]).hex()}
            for m in heard
        ],
        "got": got,
        "late": len(late),
        "abort": [abort.returncode, abort.stderr.strip()[-300:], aborts],
        "counters": vars(rx.counters),
        "auth": dict(rx.auth.counters.rejected) if rx.auth else {},
        "bad_samples": transports[1].bad_samples,
    }
    spy.close()
    for link in links:
        link.close()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
