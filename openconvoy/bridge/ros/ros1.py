"""ROS 1 from the project's Python: a node in a system-``python3`` subprocess, and roscore.

Debian packages ROS 1 (``python3-rospy``, ``roscore``) for its own ``/usr/bin/python3``;
OpenConvoy runs in its own environment (another Python, its own packages). Rather than
putting Debian's ``dist-packages`` on our path (compiled modules for another Python, and
rospy's one node per process), each ROS 1 node runs ``ros1_agent.py`` under the system
Python and talks JSON lines with us (``Ros1Node``): subscribe, publish, call and serve
services, with messages as dicts. ``OPENCONVOY_ROS1_PYTHON`` names another interpreter.

The node reaches the master named by ``ROS_MASTER_URI`` (as any ROS 1 node);
``Roscore`` starts a private master on a free port for tests and demos.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openconvoy.core.errors import DependencyMissing, LinkError

AGENT = Path(__file__).resolve().parent / "ros1_agent.py"
MSG_DIR = Path(__file__).resolve().parent / "mavros_msgs"
"""Our ``mavros_msgs`` subset: MAVROS's own .msg/.srv text (see its README)."""

INSTALL_HINT = (
    "ROS 1 needs Debian's rospy and roscore: apt-get install python3-rospy python3-roslaunch "
    "python3-genpy python3-std-msgs python3-geometry-msgs python3-nav-msgs python3-sensor-msgs "
    "ros-std-msgs ros-geometry-msgs"
)

Handler = Callable[[dict[str, Any]], None]


def system_python() -> str:
    """The interpreter that has rospy (``OPENCONVOY_ROS1_PYTHON``, default /usr/bin/python3)."""
    return os.environ.get("OPENCONVOY_ROS1_PYTHON", "/usr/bin/python3")


def ros1_available() -> str | None:
    """None when rospy and roscore are installed, else why not (one line)."""
    py = system_python()
    if not Path(py).exists():
        return f"{py} not found. {INSTALL_HINT}"
    if shutil.which("roscore") is None:
        return f"roscore not found. {INSTALL_HINT}"
    r = subprocess.run([py, "-c", "import rospy, genpy"], capture_output=True, timeout=60)
    if r.returncode != 0:
        return f"{py} cannot import rospy/genpy. {INSTALL_HINT}"
    return None


def _gen_dir(msg_dir: Path = MSG_DIR) -> Path:
    """Where genpy's classes of our ``mavros_msgs`` go (per user, per definition set)."""
    import hashlib

    digest = hashlib.sha256()
    for f in sorted(msg_dir.rglob("*.*")):
        digest.update(f.name.encode() + f.read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "openconvoy"
    return base / f"ros1-mavros_msgs-{digest.hexdigest()[:12]}"


def ros_env(master_uri: str | None = None) -> dict[str, str]:
    """The environment of a ROS 1 process: the master, loopback addresses (works inside a
    private network namespace, where the host name may not resolve), logs in a temp dir."""
    env = dict(os.environ)
    if master_uri is not None:
        env["ROS_MASTER_URI"] = master_uri
    env.setdefault("ROS_HOSTNAME", "127.0.0.1")
    env.setdefault("ROS_HOME", str(Path(tempfile.gettempdir()) / "openconvoy-ros"))
    env.pop("PYTHONPATH", None)  # our venv's packages are not for the system Python
    env.pop("PYTHONHOME", None)
    return env


class Ros1Node:
    """One ROS 1 node (``name``, absolute, e.g. ``/openconvoy_vehicle_1``) in a subprocess.

    Callbacks run on this object's reader thread; keep them short. ``call`` blocks.
    Raises ``LinkError`` when the node does not come up within ``timeout_s``.
    """

    ROS = "ROS 1"

    def __init__(
        self,
        name: str,
        master_uri: str | None = None,
        timeout_s: float = 30.0,
        msg_dir: Path = MSG_DIR,
    ) -> None:
        argv, env = self._agent(name, master_uri, msg_dir)
        self._proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
            env=env,
        )
        self._lock = threading.Lock()
        self._subs: dict[str, list[Handler]] = {}
        self._servers: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {}
        self._replies: dict[int, tuple[threading.Event, list[Any]]] = {}
        self._ids = itertools.count(1)
        self._ready = threading.Event()
        self.errors: list[str] = []
        self.name = ""
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"ros1 {name}")
        self._reader.start()
        threading.Thread(target=self._drain_stderr, daemon=True).start()
        deadline = time.monotonic() + timeout_s
        while not self._ready.wait(0.1):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                break
        if not self._ready.is_set():
            time.sleep(0.2)  # the last stderr lines
            tail = "; ".join(self.errors[-3:])
            self.close()
            raise LinkError(f"{self.ROS} node {name} did not start within {timeout_s:g} s {tail}")

    def _agent(
        self, name: str, master_uri: str | None, msg_dir: Path
    ) -> tuple[list[str], dict[str, str]]:
        """The agent's command line and environment (``Ros2Node`` has its own)."""
        why = None if Path(system_python()).exists() else ros1_available()
        if why:
            raise DependencyMissing(why)
        gen = _gen_dir(msg_dir)
        gen.parent.mkdir(parents=True, exist_ok=True)
        argv = [system_python(), str(AGENT), name.lstrip("/"), str(msg_dir), str(gen)]
        return argv, ros_env(master_uri)

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def _drain_stderr(self) -> None:
        assert self._proc.stderr is not None
        for line in self._proc.stderr:
            if line.strip():
                self.errors.append(line.strip())
                del self.errors[:-50]

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            kind = ev.get("ev")
            if kind == "msg":
                for cb in self._subs.get(ev["topic"], ()):
                    cb(ev["msg"])
            elif kind == "reply":
                slot = self._replies.pop(ev["id"], None)
                if slot is not None:
                    slot[1].append(ev)
                    slot[0].set()
            elif kind == "request":
                threading.Thread(target=self._answer, args=(ev,), daemon=True).start()
            elif kind == "ready":
                self.name = ev["node"]
                self._ready.set()
            elif kind == "error":
                self.errors.append(ev["error"])

    def _answer(self, ev: dict[str, Any]) -> None:
        server = self._servers.get(ev["service"])
        resp = server(ev["req"]) if server is not None else None
        self._send({"op": "respond", "id": ev["id"], "resp": resp})

    def _send(self, obj: dict[str, Any]) -> None:
        line = json.dumps(obj, allow_nan=True)
        with self._lock:
            if self._proc.stdin is None or self._proc.poll() is not None:
                return
            try:
                self._proc.stdin.write(line + "\n")
                self._proc.stdin.flush()
            except (BrokenPipeError, ValueError, OSError):
                pass

    def subscribe(
        self,
        topic: str,
        type_name: str,
        callback: Handler,
        nodelay: bool = False,
        any_md5: bool = False,
    ) -> None:
        """Call ``callback(msg_dict)`` for each message on ``topic`` (``pkg/Type``);
        ``nodelay``: ask the publisher to send without Nagle's delay (TCP_NODELAY);
        ``any_md5``: take any publisher of the topic (MD5 ``*``) and decode its bytes as
        ``type_name`` (for a type whose versions differ only in constants)."""
        self._subs.setdefault(topic, []).append(callback)
        self._send(
            {"op": "sub", "topic": topic, "type": type_name, "nodelay": nodelay, "any_md5": any_md5}
        )

    def advertise(self, topic: str, type_name: str, latch: bool = False) -> None:
        self._send({"op": "adv", "topic": topic, "type": type_name, "latch": latch})

    def publish(self, topic: str, msg: dict[str, Any]) -> None:
        """Publish on an advertised topic; non-blocking (a pipe write)."""
        self._send({"op": "pub", "topic": topic, "msg": msg})

    def serve(
        self, service: str, type_name: str, handler: Callable[[dict[str, Any]], dict[str, Any]]
    ) -> None:
        """Answer calls of ``service`` with ``handler(request) -> response`` (dicts)."""
        self._servers[service] = handler
        self._send({"op": "serve", "service": service, "type": type_name})

    def _request(self, obj: dict[str, Any], timeout_s: float) -> dict[str, Any]:
        rid = next(self._ids)
        slot: tuple[threading.Event, list[Any]] = (threading.Event(), [])
        self._replies[rid] = slot
        self._send({**obj, "id": rid})
        if not slot[0].wait(timeout_s):
            self._replies.pop(rid, None)
            raise TimeoutError(
                f"{obj.get('service') or obj.get('type')}: no answer in {timeout_s:g} s"
            )
        ev = slot[1][0]
        if "error" in ev:
            raise LinkError(f"{obj.get('service') or obj.get('type')}: {ev['error']}")
        return dict(ev["resp"])

    def call(
        self, service: str, type_name: str, req: dict[str, Any], timeout_s: float = 5.0
    ) -> dict[str, Any]:
        """Call a service (waiting up to ``timeout_s`` for it to exist and answer)."""
        return self._request(
            {"op": "call", "service": service, "type": type_name, "req": req, "timeout": timeout_s},
            timeout_s + 1.0,
        )

    def md5(self, type_name: str, timeout_s: float = 10.0) -> str:
        """The MD5 sum ROS 1 gives a message or service type (``pkg/Type``)."""
        return str(self._request({"op": "md5", "type": type_name}, timeout_s)["md5"])

    def close(self) -> None:
        """End the node (idempotent)."""
        if self._proc.poll() is None:
            try:
                assert self._proc.stdin is not None
                self._proc.stdin.close()
            except OSError:
                pass
            try:
                self._proc.wait(3.0)
            except subprocess.TimeoutExpired:
                self._proc.terminate()
                try:
                    self._proc.wait(3.0)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait()


def stamp(t_s: float) -> dict[str, Any]:
    """A ``std_msgs/Header`` (as a dict) stamped ``t_s`` (s since the epoch)."""
    return {"seq": 0, "stamp": t_s, "frame_id": ""}


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Roscore:
    """A private ROS 1 master (``roscore -p PORT``, Debian's), for tests and demos."""

    def __init__(self, port: int | None = None, timeout_s: float = 30.0) -> None:
        why = ros1_available()
        if why:
            raise DependencyMissing(why)
        self.port = port or free_tcp_port()
        self.uri = f"http://127.0.0.1:{self.port}/"
        self._proc = subprocess.Popen(
            ["roscore", "-p", str(self.port)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=ros_env(self.uri),
            start_new_session=True,
        )
        deadline = time.monotonic() + timeout_s
        while not self._up():
            if self._proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise LinkError(f"roscore on port {self.port} did not come up")
            time.sleep(0.2)

    def _up(self) -> bool:
        import xmlrpc.client

        try:
            answer: Any = xmlrpc.client.ServerProxy(self.uri).getSystemState("/openconvoy")
            return bool(answer[0] == 1)
        except OSError:
            return False

    def close(self) -> None:
        """Stop the master and its rosout (its process group)."""
        if self._proc.poll() is None:
            import signal

            os.killpg(self._proc.pid, signal.SIGINT)
            try:
                self._proc.wait(10.0)
            except subprocess.TimeoutExpired:
                os.killpg(self._proc.pid, signal.SIGKILL)
                self._proc.wait()

    def __enter__(self) -> Roscore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def finite(x: Any) -> float:
    """A float from a ROS message field, NaN when absent or not a number."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v
