"""A ROS 2 node in its own process: the one place OpenConvoy runs rclpy.

Run by the Python of the ROS 2 environment (``.venv-ros2``: the rclpy wheels from PyPI,
Jazzy, Fast DDS), never imported by the package: ``bridge.ros.ros2.Ros2Node`` starts it as
a subprocess and speaks the same JSON lines with it as ``Ros1Node`` does with
``ros1_agent.py``, so the project's Python never loads rclpy (whose wheels re-execute
every Python of their environment with their own ``LD_LIBRARY_PATH``). Only the standard
library and rclpy (and the interface packages) are used here.

Arguments: ``NODE_NAME``: the node's name, absolute (``/vehicle_1/openconvoy``: namespace
and name).

Requests (one JSON object a line on stdin), answers and events on stdout, as
``ros1_agent.py``; types are named ``pkg/Type`` (``pkg.msg.Type`` or ``pkg.srv.Type``) and
each ``sub``/``adv`` carries its QoS: ``"sensor"`` (rclpy's ``qos_profile_sensor_data``:
best effort, volatile, depth 5) or ``"state"`` (reliable, transient local, depth 10),
the two profiles MAVROS 2's plugins use (``bridge.ros.ros2.qos_for``).

- ``{"op": "sub", "topic", "type", "qos"}``; each message comes as
  ``{"ev": "msg", "topic", "msg": {...}}``.
- ``{"op": "adv", "topic", "type", "qos"}``; ``{"op": "pub", "topic", "msg"}``.
- ``{"op": "call", "id", "service", "type", "req", "timeout"}`` → ``{"ev": "reply", ...}``.
- ``{"op": "serve", "service", "type"}``: each call comes as ``{"ev": "request", ...}`` and
  waits for ``{"op": "respond", "id", "resp"}`` (``resp`` null: the default response).
- ``{"op": "publishers", "id", "topic"}``: the topic's publishers as discovered
  (node name, type, RIHS01 type hash, reliability).

Times (``builtin_interfaces/Time``) travel as float seconds; a dict field the message does
not have (ROS 1's ``header.seq``) is ignored; arrays as lists.
"""

import importlib
import json
import os
import sys
import threading


def _cls(type_name, kind="msg"):
    pkg, name = type_name.split("/")[0], type_name.split("/")[-1]
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def _is_msg(value):
    return hasattr(value, "get_fields_and_field_types")


def to_dict(value):
    """An rclpy message (or field value) as JSON-able data."""
    if _is_msg(value):
        if type(value).__name__ == "Time" and hasattr(value, "nanosec"):
            return value.sec + value.nanosec * 1e-9
        return {f: to_dict(getattr(value, f)) for f in value.get_fields_and_field_types()}
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if hasattr(value, "tolist"):  # numpy and array.array
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [to_dict(v) for v in value]
    return value


def from_dict(cls, data):
    """A message of class ``cls`` from ``to_dict``'s data (missing fields default)."""
    msg = cls()
    if cls.__name__ == "Time" and not isinstance(data, dict):
        t = float(data)
        msg.sec = int(t // 1)
        msg.nanosec = min(int(round((t - msg.sec) * 1e9)), 999_999_999)
        return msg
    for field, typ in cls.get_fields_and_field_types().items():
        if field not in data:
            continue
        v = data[field]
        current = getattr(msg, field)
        if _is_msg(current):
            v = from_dict(type(current), v)
        elif typ.startswith("sequence<") and "/" in typ:
            sub = _cls(typ[len("sequence<") :].split(",")[0].rstrip(">").replace("/msg/", "/"))
            v = [from_dict(sub, x) for x in v]
        elif isinstance(current, float):
            v = float(v)
        elif isinstance(current, bool):
            v = bool(v)
        elif isinstance(current, int):
            v = int(v)
        setattr(msg, field, v)
    return msg


class Agent:
    def __init__(self, node_name):
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import (
            DurabilityPolicy,
            QoSProfile,
            ReliabilityPolicy,
            qos_profile_sensor_data,
        )

        rclpy.init(args=[])
        ns, _, name = node_name.rpartition("/")
        self.rclpy = rclpy
        # No parameter services and no /rosout: fewer entities for the executor to wait on.
        self.node = rclpy.create_node(
            name, namespace=ns or "/", start_parameter_services=False, enable_rosout=False
        )
        self.group = ReentrantCallbackGroup()
        self.qos = {
            "sensor": qos_profile_sensor_data,
            "state": QoSProfile(
                depth=10,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
            ),
            "default": QoSProfile(depth=10),
        }
        self.lock = threading.Lock()
        self.pubs = {}
        self.keep = []
        self.pending = {}
        self.next_id = 0
        # One thread spins (the multi-threaded executor costs several times the CPU per
        # message; rclpy 7.1's events executor took no entities created after it started);
        # service handlers are coroutines that wait for our answer without blocking it.
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.wake = self.node.create_guard_condition(lambda: None)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def emit(self, obj):
        line = json.dumps(obj, allow_nan=True)
        with self.lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    def handle(self, req):
        op = req["op"]
        qos = self.qos[req.get("qos", "default")]
        if op == "sub":
            topic = req["topic"]

            def cb(msg, topic=topic):
                self.emit({"ev": "msg", "topic": topic, "msg": to_dict(msg)})

            self.keep.append(
                self.node.create_subscription(
                    _cls(req["type"]), topic, cb, qos, callback_group=self.group
                )
            )
        elif op == "adv":
            cls = _cls(req["type"])
            self.pubs[req["topic"]] = (self.node.create_publisher(cls, req["topic"], qos), cls)
        elif op == "pub":
            pub, cls = self.pubs[req["topic"]]
            pub.publish(from_dict(cls, req["msg"]))
        elif op == "call":
            threading.Thread(target=self.call, args=(req,), daemon=True).start()
        elif op == "serve":
            self.serve(req["service"], req["type"])
        elif op == "respond":
            future = self.pending.pop(req["id"], None)
            if future is not None:
                future.set_result(req["resp"])
                self.wake.trigger()  # the executor resumes the waiting handler
        elif op == "publishers":
            infos = self.node.get_publishers_info_by_topic(req["topic"])
            resp = [
                {
                    "node": f"{i.node_namespace.rstrip('/')}/{i.node_name}",
                    "type": i.topic_type,
                    "type_hash": str(i.topic_type_hash),
                    "reliability": i.qos_profile.reliability.name,
                    "durability": i.qos_profile.durability.name,
                }
                for i in infos
            ]
            self.emit({"ev": "reply", "id": req["id"], "resp": {"publishers": resp}})
        else:
            raise ValueError(f"unknown op {op!r}")

    def call(self, req):
        try:
            srv = _cls(req["type"], "srv")
            timeout = float(req.get("timeout", 5.0))
            client = self.node.create_client(srv, req["service"], callback_group=self.group)
            try:
                if not client.wait_for_service(timeout_sec=timeout):
                    raise TimeoutError(f"service {req['service']} not available")
                done = threading.Event()
                future = client.call_async(from_dict(srv.Request, req.get("req", {})))
                future.add_done_callback(lambda f: done.set())
                if not done.wait(timeout):
                    raise TimeoutError(f"no answer in {timeout:g} s")
                resp = to_dict(future.result())
            finally:
                self.node.destroy_client(client)
            self.emit({"ev": "reply", "id": req["id"], "resp": resp})
        except Exception as exc:  # noqa: BLE001 - reported to the caller, one line
            self.emit({"ev": "reply", "id": req["id"], "error": f"{type(exc).__name__}: {exc}"})

    def serve(self, service, type_name):
        srv = _cls(type_name, "srv")

        async def handler(request, response):
            from rclpy.task import Future

            with self.lock:
                self.next_id += 1
                rid = self.next_id
            future = Future()
            self.pending[rid] = future
            self.emit({"ev": "request", "id": rid, "service": service, "req": to_dict(request)})
            resp = await future
            if resp is None:
                return response  # no answer: the default response (e.g. success false)
            return from_dict(srv.Response, resp)

        self.keep.append(self.node.create_service(srv, service, handler, callback_group=self.group))


def main():
    agent = Agent(sys.argv[1])
    name = agent.node.get_fully_qualified_name()
    agent.emit({"ev": "ready", "node": name})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            agent.handle(json.loads(line))
        except Exception as exc:  # noqa: BLE001 - one line back; the node keeps running
            agent.emit({"ev": "error", "error": f"{type(exc).__name__}: {exc}"})
    # Our parent closed stdin (or died): leave now. A clean rclpy shutdown can wait on the
    # executor's thread; the node's peers see it go by DDS's liveliness either way.
    sys.stdout.flush()
    os._exit(0)


if __name__ == "__main__":
    main()
