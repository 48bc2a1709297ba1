"""A ROS 1 node in its own process: the one place OpenConvoy runs rospy.

Run by the system's ``python3`` (Debian's ``python3-rospy``), never imported by the
package: ``bridge.ros.ros1.Ros1Node`` starts it as a subprocess and speaks JSON lines with
it over stdin/stdout, so the project's Python (any version, its own venv) never loads
rospy, and several nodes (a link, a stand-in MAVROS) can run side by side, each its own
ROS node as in a real robot. Only the standard library, rospy and genpy are used here.

Arguments: ``NODE_NAME MSG_DIR GEN_DIR``: the node name; a directory with our
``mavros_msgs`` definitions (``msg/*.msg``, ``srv/*.srv``: MAVROS's own text); where to
generate their Python classes with genpy (done once, reused).

Requests (one JSON object a line on stdin), answers and events on stdout:

- ``{"op": "sub", "topic", "type", "nodelay", "any_md5"}``: subscribe (``nodelay``: ask the
  publisher for TCP_NODELAY, as roscpp's ``TransportHints().tcpNoDelay()``; ``any_md5``:
  accept a publisher whose definition differs only in what does not travel, e.g.
  constants); each message comes as ``{"ev": "msg", "topic", "msg": {...}}``.
- ``{"op": "adv", "topic", "type", "latch"}``; ``{"op": "pub", "topic", "msg"}``.
- ``{"op": "call", "id", "service", "type", "req", "timeout"}``: a service call in a
  thread; ``{"ev": "reply", "id", "resp"}`` or ``{"ev": "reply", "id", "error"}``.
- ``{"op": "serve", "service", "type"}``: a service server; each call comes as
  ``{"ev": "request", "id", "service", "req"}`` and waits (10 s) for
  ``{"op": "respond", "id", "resp"}``.
- ``{"op": "md5", "id", "type"}``: ``{"ev": "reply", "id", "resp": {"md5": ...}}`` (a
  message or service type's MD5 sum as ROS 1 computes it).

Times travel as float seconds; ``uint8[]`` as lists of ints.
"""

import importlib
import json
import os
import sys
import threading


def _generate(msg_dir, gen_dir):
    """Python classes of the ``mavros_msgs`` subset (genpy, as catkin would build them),
    generated once into ``gen_dir`` (built beside it and renamed into place, so nodes
    starting together never see half a package)."""
    if not os.path.exists(os.path.join(gen_dir, "mavros_msgs", ".generated")):
        import shutil
        import tempfile

        from genpy.generator import MsgGenerator, SrvGenerator

        parent = os.path.dirname(gen_dir)
        os.makedirs(parent, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=".gen-", dir=parent)
        pkg_dir = os.path.join(tmp, "mavros_msgs")
        search = {
            "mavros_msgs": [os.path.join(msg_dir, "msg")],
            "std_msgs": ["/usr/share/std_msgs/msg"],
            "geometry_msgs": ["/usr/share/geometry_msgs/msg"],
        }
        for sub, gen, ext in (("msg", MsgGenerator(), ".msg"), ("srv", SrvGenerator(), ".srv")):
            files = sorted(
                os.path.join(msg_dir, sub, f)
                for f in os.listdir(os.path.join(msg_dir, sub))
                if f.endswith(ext)
            )
            out = os.path.join(pkg_dir, sub)
            rc = gen.generate_messages("mavros_msgs", files, out, search)
            if rc:
                raise RuntimeError(f"genpy could not generate mavros_msgs/{sub}")
            names = [os.path.basename(f)[: -len(ext)] for f in files]
            with open(os.path.join(out, "__init__.py"), "w") as f:
                f.writelines(f"from ._{n} import *\n" for n in names)
        with open(os.path.join(pkg_dir, "__init__.py"), "w") as f:
            f.write("")
        with open(os.path.join(pkg_dir, ".generated"), "w") as f:
            f.write("ok\n")
        try:
            os.rename(tmp, gen_dir)
        except OSError:  # another node got there first: use its copy
            shutil.rmtree(tmp, ignore_errors=True)
    sys.path.insert(0, gen_dir)


def _cls(type_name, kind="msg"):
    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)


def to_dict(value):
    """A genpy message (or field value) as JSON-able data."""
    import genpy

    if isinstance(value, genpy.TVal):
        return value.to_sec()
    if hasattr(value, "__slots__") and hasattr(value, "_slot_types"):
        return {s: to_dict(getattr(value, s)) for s in value.__slots__}
    if isinstance(value, bytes):
        return list(value)
    if isinstance(value, (list, tuple)):
        return [to_dict(v) for v in value]
    return value


def from_dict(cls, data):
    """A genpy message of class ``cls`` from ``to_dict``'s data (missing fields default)."""
    import genpy
    import rospy

    msg = cls()
    for slot, typ in zip(cls.__slots__, cls._slot_types):
        if slot not in data:
            continue
        v = data[slot]
        if typ in ("time", "duration"):
            v = rospy.Time.from_sec(v) if typ == "time" else rospy.Duration.from_sec(v)
        elif typ in ("uint8[]", "char[]") or (typ.startswith("uint8[") and typ.endswith("]")):
            v = bytes(v)
        elif "/" in typ or typ == "Header":
            base = typ.split("[")[0]
            base = "std_msgs/Header" if base == "Header" else base
            sub = genpy.message.get_message_class(base)
            v = [from_dict(sub, x) for x in v] if typ.endswith("]") else from_dict(sub, v)
        setattr(msg, slot, v)
    return msg


class Agent:
    def __init__(self):
        import rospy

        self.rospy = rospy
        self.lock = threading.Lock()
        self.pubs = {}
        self.keep = []
        self.pending = {}
        self.next_id = 0

    def emit(self, obj):
        line = json.dumps(obj, allow_nan=True)
        with self.lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    def handle(self, req):
        op = req["op"]
        rospy = self.rospy
        if op == "sub":
            topic, cls = req["topic"], _cls(req["type"])
            if req.get("any_md5"):
                # Any publisher's definition of this wire format (rospy.AnyMsg: MD5 "*", as
                # rostopic and rosbag subscribe), decoded with ours.
                def cb(raw, topic=topic, cls=cls):
                    msg = cls().deserialize(raw._buff)
                    self.emit({"ev": "msg", "topic": topic, "msg": to_dict(msg)})

                wire = rospy.AnyMsg
            else:

                def cb(raw, topic=topic, cls=cls):
                    self.emit({"ev": "msg", "topic": topic, "msg": to_dict(raw)})

                wire = cls
            self.keep.append(
                rospy.Subscriber(
                    topic, wire, cb, queue_size=50, tcp_nodelay=bool(req.get("nodelay"))
                )
            )
        elif op == "adv":
            self.pubs[req["topic"]] = (
                rospy.Publisher(
                    req["topic"],
                    _cls(req["type"]),
                    queue_size=10,
                    latch=bool(req.get("latch")),
                ),
                _cls(req["type"]),
            )
        elif op == "pub":
            pub, cls = self.pubs[req["topic"]]
            pub.publish(from_dict(cls, req["msg"]))
        elif op == "call":
            threading.Thread(target=self.call, args=(req,), daemon=True).start()
        elif op == "serve":
            self.serve(req["service"], req["type"])
        elif op == "respond":
            slot = self.pending.get(req["id"])
            if slot is not None:
                slot[1] = req["resp"]
                slot[0].set()
        elif op == "md5":
            pkg, name = req["type"].split("/")
            try:
                cls = _cls(req["type"], "msg")
            except (ImportError, AttributeError):
                cls = _cls(req["type"], "srv")
            self.emit({"ev": "reply", "id": req["id"], "resp": {"md5": cls._md5sum}})
        else:
            raise ValueError(f"unknown op {op!r}")

    def call(self, req):
        rospy = self.rospy
        try:
            srv = _cls(req["type"], "srv")
            rospy.wait_for_service(req["service"], timeout=float(req.get("timeout", 5.0)))
            proxy = rospy.ServiceProxy(req["service"], srv)
            resp = proxy(from_dict(srv._request_class, req.get("req", {})))
            self.emit({"ev": "reply", "id": req["id"], "resp": to_dict(resp)})
        except Exception as exc:  # noqa: BLE001 - reported to the caller, one line
            self.emit({"ev": "reply", "id": req["id"], "error": f"{type(exc).__name__}: {exc}"})

    def serve(self, service, type_name):
        srv = _cls(type_name, "srv")

        def handler(request):
            with self.lock:
                self.next_id += 1
                rid = self.next_id
            event = threading.Event()
            slot = [event, None]
            self.pending[rid] = slot
            self.emit({"ev": "request", "id": rid, "service": service, "req": to_dict(request)})
            ok = event.wait(10.0)
            self.pending.pop(rid, None)
            if not ok or slot[1] is None:
                return None  # rospy reports a failed call to the client
            return from_dict(srv._response_class, slot[1])

        self.keep.append(self.rospy.Service(service, srv, handler))


def main():
    name, msg_dir, gen_dir = sys.argv[1:4]
    _generate(msg_dir, gen_dir)
    agent = Agent()
    agent.rospy.init_node(name, anonymous=False, disable_signals=True)
    agent.emit({"ev": "ready", "node": agent.rospy.get_name()})
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            agent.handle(json.loads(line))
        except Exception as exc:  # noqa: BLE001 - one line back; the node keeps running
            agent.emit({"ev": "error", "error": f"{type(exc).__name__}: {exc}"})
    agent.rospy.signal_shutdown("stdin closed")


if __name__ == "__main__":
    main()
