"""A ROS 2 node without ROS: the ``ap-dds`` link's topics and service calls through Cyclone
DDS directly, in its own process, speaking ``ros2_agent.py``'s JSON lines
(``bridge.ros.ros2.CycloneNode`` starts it; ``python -m openconvoy.bridge.ros.cyclone_agent
NODE_NAME``). Only the ops the link uses: ``sub``, ``adv``, ``pub``, ``call``.

ROS 2's mapping onto DDS, as rmw does it and as ArduPilot's ``AP_DDS_Topic_Table.h`` /
``AP_DDS_Service_Table.h`` spell it: topic ``/ap/navsat`` is DDS topic ``rt/ap/navsat``;
service ``/ap/arm_motors`` is a request topic ``rq/ap/arm_motorsRequest`` and a reply topic
``rr/ap/arm_motorsReply`` (types ``ardupilot_msgs::srv::dds_::ArmMotors_Request_`` and
``_Response_``); XCDR1. A request carries the plain request (no in-payload header: that is
rmw_cyclonedds's own convention, which Fast DDS services do not read, ros2/rmw_cyclonedds
#184); the replier (AP_DDS's XRCE agent, or rmw_fastrtps) correlates by the RTPS sample
identity, which cyclonedds-python does not expose, so this node makes one call at a time
and takes the first reply after its request (one client per vehicle namespace).

QoS (``AP_DDS_Topic_Table.h``): ``"sensor"`` best effort, volatile, keep last 5;
``"state"`` (``/ap/status``) reliable, transient local. Service endpoints are made per
call: the request writer reliable and transient local (AP_DDS's replier asks transient
local; a volatile reader, rclpy's, matches it too), the reply reader reliable, volatile.

Environment: ``OPENCONVOY_DDS_IFACE`` keeps Cyclone on that interface (tests: the private
namespace's veth), else Cyclone's own configuration (``CYCLONEDDS_URI``); the domain is
``ROS_DOMAIN_ID`` (default 0).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import Any

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from openconvoy.bridge.ros.apdds_msgs import MESSAGES, SERVICES, from_dict, to_dict
from openconvoy.comms.dds import dds_topic, interface_config

QOS = {
    "sensor": Qos(
        Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5)
    ),
    "state": Qos(
        Policy.Reliability.Reliable(1_000_000_000),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(10),
    ),
}
REQUEST_QOS = Qos(
    Policy.Reliability.Reliable(1_000_000_000),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)
REPLY_QOS = Qos(
    Policy.Reliability.Reliable(1_000_000_000),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(5),
)
POLL_S = 0.005


def service_topics(service: str) -> tuple[str, str]:
    """The request and reply DDS topics of a ROS 2 service (``/ap/arm_motors`` →
    ``rq/ap/arm_motorsRequest``, ``rr/ap/arm_motorsReply``)."""
    base = dds_topic(service)[len("rt/") :]
    return f"rq/{base}Request", f"rr/{base}Reply"


class Agent:
    def __init__(self, node_name: str) -> None:
        domain = int(os.environ.get("ROS_DOMAIN_ID", "0"))
        iface = os.environ.get("OPENCONVOY_DDS_IFACE")
        if iface:
            self.domain = Domain(domain, interface_config(iface))
        self.dp = DomainParticipant(domain)
        self.name = node_name
        self.lock = threading.Lock()
        self.topics: dict[str, Topic] = {}
        self.readers: list[tuple[str, DataReader, type]] = []
        self.writers: dict[str, tuple[DataWriter, type]] = {}
        self.bad_samples = 0
        self.call_lock = threading.Lock()
        threading.Thread(target=self.spin, daemon=True).start()

    def emit(self, obj: dict[str, Any]) -> None:
        line = json.dumps(obj, allow_nan=True)
        with self.lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    def topic(self, name: str, kind: type) -> Topic:
        if name not in self.topics:
            self.topics[name] = Topic(self.dp, name, kind)
        return self.topics[name]

    def spin(self) -> None:
        """Hand every sample of every subscription to our parent, oldest first."""
        while True:
            for ros_topic, reader, kind in list(self.readers):
                try:
                    samples = reader.take(N=64)
                except Exception:  # noqa: BLE001 (bad CDR: network input, counted)
                    self.bad_samples += 1
                    continue
                for s in samples:
                    if isinstance(s, kind):
                        self.emit({"ev": "msg", "topic": ros_topic, "msg": to_dict(s)})
            time.sleep(POLL_S)

    def handle(self, req: dict[str, Any]) -> None:
        op = req["op"]
        if op == "sub":
            kind = MESSAGES[req["type"]]
            qos = QOS[req.get("qos", "sensor")]
            reader = DataReader(self.dp, self.topic(dds_topic(req["topic"]), kind), qos=qos)
            self.readers.append((req["topic"], reader, kind))
        elif op == "adv":
            kind = MESSAGES[req["type"]]
            qos = QOS[req.get("qos", "sensor")]
            writer = DataWriter(self.dp, self.topic(dds_topic(req["topic"]), kind), qos=qos)
            self.writers[req["topic"]] = (writer, kind)
        elif op == "pub":
            writer, kind = self.writers[req["topic"]]
            writer.write(from_dict(kind, req["msg"]))
        elif op == "call":
            threading.Thread(target=self.call, args=(req,), daemon=True).start()
        else:
            raise ValueError(f"unknown op {op!r}")

    def call(self, req: dict[str, Any]) -> None:
        try:
            with self.call_lock:
                resp = self._call(req["service"], req["type"], req.get("req", {}), req)
            self.emit({"ev": "reply", "id": req["id"], "resp": resp})
        except Exception as exc:  # noqa: BLE001 - reported to the caller, one line
            self.emit({"ev": "reply", "id": req["id"], "error": f"{type(exc).__name__}: {exc}"})

    def _call(self, service: str, type_name: str, body: dict[str, Any], req: dict) -> dict:
        request_kind, reply_kind = SERVICES[type_name]
        timeout = float(req.get("timeout", 5.0))
        deadline = time.monotonic() + timeout
        rq, rr = service_topics(service)
        # Fresh endpoints per call (as rclpy's agent makes a client per call): no reply of
        # an earlier call, no request replayed to a server that comes later.
        reader = DataReader(self.dp, self.topic(rr, reply_kind), qos=REPLY_QOS)
        writer = DataWriter(self.dp, self.topic(rq, request_kind), qos=REQUEST_QOS)
        try:
            while not (writer.get_matched_subscriptions() and reader.get_matched_publications()):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"service {service} not available")
                time.sleep(0.01)
            writer.write(from_dict(request_kind, body))
            while time.monotonic() < deadline:
                for s in reader.take(N=8):
                    if isinstance(s, reply_kind):
                        return dict(to_dict(s))
                time.sleep(0.005)
            raise TimeoutError(f"no answer in {timeout:g} s")
        finally:
            writer.__del__()  # cyclonedds has no public delete; this one is idempotent
            reader.__del__()


def main() -> None:
    agent = Agent(sys.argv[1])
    agent.emit({"ev": "ready", "node": agent.name})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            agent.handle(json.loads(line))
        except Exception as exc:  # noqa: BLE001 - one line back; the node keeps running
            agent.emit({"ev": "error", "error": f"{type(exc).__name__}: {exc}"})
    sys.stdout.flush()
    os._exit(0)  # our parent closed stdin: leave; DDS liveliness tells the peers


if __name__ == "__main__":
    main()
