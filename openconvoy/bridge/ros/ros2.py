"""ROS 2 from the project's Python: a node in a subprocess of the ROS 2 environment.

ROS 2 comes from PyPI's rclpy wheels (Jazzy, Fast DDS), installed in their own virtual
environment (``make ros2``: ``.venv-ros2``; ``OPENCONVOY_ROS2_VENV`` names another): their
bootstrap re-executes every Python of that environment with its own ``LD_LIBRARY_PATH``,
so they stay out of the project's. Each ROS 2 node runs ``ros2_agent.py`` there and talks
the JSON lines of ``Ros1Node`` with us (``Ros2Node``).

``mavros_msgs`` for ROS 2: the same MAVROS text as for ROS 1 (``mavros_msgs/``), built once
with rosidl (``rosidl_generate_interfaces``, CMake, the C compiler) into a per-user cache,
as colcon would build MAVROS's own package; ``type_hashes`` gives their RIHS01 type hashes.

DDS discovery multicasts on every interface: nodes start with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless the environment says otherwise, and tests
run them inside a private network namespace (``LoopbackNetns``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from openconvoy.bridge.ros.ros1 import MSG_DIR, Ros1Node
from openconvoy.core.errors import DependencyMissing, LinkError

AGENT = Path(__file__).resolve().parent / "ros2_agent.py"
FASTDDS_PROFILE = Path(__file__).resolve().parent / "fastdds_discovery.xml"
"""Fast DDS's default participant with a longer burst of discovery announcements."""
REPO_VENV = Path(__file__).resolve().parents[3] / ".venv-ros2"
INSTALL_HINT = (
    "ROS 2 needs the rclpy wheels in their own environment: run `make ros2` (docs/ros.md)"
)
MAVROS_MSGS = ("State", "PositionTarget", "GlobalPositionTarget")
MAVROS_SRVS = ("SetMode", "CommandBool")
AP_MSG_DIR = Path(__file__).resolve().parent / "ardupilot_msgs"
"""Our subset of ArduPilot's ``ardupilot_msgs`` (the ``ap-dds`` link's services and status)."""
AP_MSGS = ("Status",)
AP_SRVS = ("ArmMotors", "ModeSwitch")
OC_MSG_DIR = Path(__file__).resolve().parents[2] / "msg"
"""Our own ``openconvoy_msgs`` (.msg files directly in ``openconvoy/msg``): the run bags' and
V2V over ROS 2's types."""
OC_MSGS = ("ConvoyStatus", "V2VBytes")
NETNS_ENV = "OPENCONVOY_ROS2_NETNS"
"""The pid of a process whose network namespace ROS 2 nodes join (``LoopbackNetns``)."""


def ros2_venv() -> Path:
    """The ROS 2 environment (``OPENCONVOY_ROS2_VENV``, default the checkout's .venv-ros2)."""
    return Path(os.environ.get("OPENCONVOY_ROS2_VENV", REPO_VENV))


def ros2_python() -> Path:
    return ros2_venv() / "bin" / "python"


def ros2_available() -> str | None:
    """None when the ROS 2 environment has rclpy, else why not (one line)."""
    py = ros2_python()
    if not py.exists():
        return f"{py} not found. {INSTALL_HINT}"
    r = subprocess.run([str(py), "-c", "import rclpy"], capture_output=True, timeout=120)
    if r.returncode != 0:
        return f"{py} cannot import rclpy. {INSTALL_HINT}"
    return None


def qos_for(topic: str) -> str:
    """The QoS MAVROS 2 gives a topic (mavros 2.12.0): ``state`` is published reliable,
    transient local, depth 10 (``sys_status.cpp``: ``rclcpp::QoS(10).transient_local()``);
    the sensor topics and setpoint subscriptions use ``rclcpp::SensorDataQoS()``
    (``global_position.cpp``, ``imu.cpp``, ``setpoint_raw.cpp``, ``setpoint_velocity.cpp``).
    The ``ap-dds`` topics follow ArduPilot's ``AP_DDS_Topic_Table.h``: ``/ap/status``
    reliable, transient local (depth 1 there); the others (navsat, pose/filtered,
    twist/filtered, cmd_vel) best effort, volatile, depth 5."""
    return "state" if topic.rstrip("/").endswith(("/state", "/ap/status")) else "sensor"


# ---------------------------------------------------------------------- mavros_msgs build

CMAKE = """cmake_minimum_required(VERSION 3.8)
project({pkg})
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
# The PyPI wheels' exported targets name the include directory of the Python they were
# built with (/opt/python/cp311-cp311/...): point them at this Python's.
find_package(Python3 REQUIRED COMPONENTS Interpreter Development)
foreach(dep builtin_interfaces std_msgs geometry_msgs service_msgs)
  find_package(${{dep}} REQUIRED)
  if(TARGET ${{dep}}::${{dep}}__rosidl_generator_py)
    set_target_properties(${{dep}}::${{dep}}__rosidl_generator_py PROPERTIES
      INTERFACE_INCLUDE_DIRECTORIES "${{Python3_INCLUDE_DIRS}}")
  endif()
endforeach()
rosidl_generate_interfaces(${{PROJECT_NAME}} {files} DEPENDENCIES geometry_msgs std_msgs)
ament_export_dependencies(rosidl_default_runtime)
ament_package()
"""

PACKAGE_XML = """<?xml version="1.0"?>
<package format="3">
  <name>{pkg}</name>
  <version>{version}</version>
  <description>OpenConvoy's subset of {pkg}</description>
  <maintainer email="openconvoy@example.invalid">OpenConvoy</maintainer>
  <license>BSD</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>geometry_msgs</depend>
  <depend>std_msgs</depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export><build_type>ament_cmake</build_type></export>
</package>
"""


PACKAGES: dict[str, tuple[tuple[str, ...], tuple[str, ...], str]] = {
    "mavros_msgs": (MAVROS_MSGS, MAVROS_SRVS, "2.12.0"),
    "ardupilot_msgs": (AP_MSGS, AP_SRVS, "0.0.0"),
    "openconvoy_msgs": (OC_MSGS, (), "0.0.0"),
}
"""The interface packages we build: messages, services, version."""


def _interface_files(pkg: str = "mavros_msgs") -> list[str]:
    msgs, srvs, _ = PACKAGES[pkg]
    return [f"msg/{m}.msg" for m in msgs] + [f"srv/{s}.srv" for s in srvs]


def _source(msg_dir: Path, f: str) -> Path:
    """Where interface file ``f`` (``msg/X.msg``) lies under ``msg_dir``: there, or for
    ``openconvoy/msg`` (no ``msg/`` level) directly in it."""
    return msg_dir / f if (msg_dir / f).exists() else msg_dir / Path(f).name


def mavros_msgs_prefix(msg_dir: Path = MSG_DIR, pkg: str = "mavros_msgs") -> Path:
    """Where our ``pkg`` (default ``mavros_msgs``) is installed for ROS 2 (per user, per
    definition set)."""
    digest = hashlib.sha256(str(ros2_venv().resolve()).encode())
    for f in _interface_files(pkg):
        digest.update(f.encode() + _source(msg_dir, f).read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "openconvoy"
    return base / f"ros2-{pkg}-{digest.hexdigest()[:12]}"


def _site_packages(prefix: Path) -> Path:
    return prefix / "lib" / "python3.11" / "site-packages"


def build_interfaces(pkg: str) -> Path:
    """``build_mavros_msgs`` for one of ``PACKAGES`` from the package's own text."""
    dirs = {"ardupilot_msgs": AP_MSG_DIR, "openconvoy_msgs": OC_MSG_DIR}
    return build_mavros_msgs(dirs.get(pkg, MSG_DIR), pkg)


def build_mavros_msgs(msg_dir: Path = MSG_DIR, pkg: str = "mavros_msgs") -> Path:
    """Build our ``mavros_msgs`` (or ``pkg``) with rosidl once (~30 s) and return the
    install prefix; built beside it and renamed into place, so nodes starting together
    never see half of it. Raises ``LinkError`` (with CMake's last lines) when the build
    fails."""
    prefix = mavros_msgs_prefix(msg_dir, pkg)
    if (prefix / ".built").exists():
        return prefix
    why = ros2_available()
    if why:
        raise DependencyMissing(why)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".build-", dir=prefix.parent))
    try:
        src, build, inst = work / "src", work / "build", work / "install"
        files = _interface_files(pkg)
        for f in files:
            (src / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(_source(msg_dir, f), src / f)
        (src / "CMakeLists.txt").write_text(CMAKE.format(pkg=pkg, files=" ".join(files)))
        (src / "package.xml").write_text(PACKAGE_XML.format(pkg=pkg, version=PACKAGES[pkg][2]))
        build.mkdir()
        venv = ros2_venv()
        env = {
            **os.environ,
            "AMENT_PREFIX_PATH": str(venv),
            "PATH": f"{venv / 'bin'}:{os.environ.get('PATH', '')}",
        }
        env.pop("PYTHONPATH", None)
        for cmd in (
            [
                "cmake", str(src), f"-DCMAKE_PREFIX_PATH={venv}",
                f"-DCMAKE_INSTALL_PREFIX={prefix}", f"-DPython3_EXECUTABLE={ros2_python()}",
                "-DBUILD_TESTING=OFF",
            ],
            ["cmake", "--build", ".", "-j", str(os.cpu_count() or 2)],
            ["cmake", "--install", ".", "--prefix", str(inst)],
        ):  # fmt: skip
            r = subprocess.run(cmd, cwd=build, env=env, capture_output=True, text=True)
            if r.returncode != 0:
                tail = (r.stdout + r.stderr).strip().splitlines()[-8:]
                raise LinkError(f"building {pkg} for ROS 2 failed: {' | '.join(tail)}")
        (inst / ".built").write_text("ok\n")
        try:
            os.rename(inst, prefix)
        except OSError:  # another process got there first: use its copy
            pass
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return prefix


def ros2_env(prefix: Path | list[Path] | None) -> dict[str, str]:
    """The environment of a ROS 2 process: our interface packages (``prefix``: one install
    prefix or several) on its paths, discovery on this machine only unless the caller's
    environment chose otherwise."""
    env = dict(os.environ)
    for var in ("PYTHONPATH", "PYTHONHOME", "_ROS_WHEELS_BOOTSTRAP_COMPLETE", "VIRTUAL_ENV"):
        env.pop(var, None)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    env.setdefault("ROS_LOG_DIR", str(Path(tempfile.gettempdir()) / "openconvoy-ros2-log"))
    env["RCUTILS_LOGGING_USE_STDOUT"] = "0"  # stdout carries our JSON lines
    prefixes = [prefix] if isinstance(prefix, Path) else list(prefix or [])
    if prefixes:
        env["PYTHONPATH"] = ":".join(str(_site_packages(p)) for p in prefixes)
        env["LD_LIBRARY_PATH"] = ":".join(
            [str(p / "lib") for p in prefixes]
            + ([os.environ["LD_LIBRARY_PATH"]] if os.environ.get("LD_LIBRARY_PATH") else [])
        )
        env["AMENT_PREFIX_PATH"] = ":".join([str(p) for p in prefixes] + [str(ros2_venv())])
    return env


class Ros2Node(Ros1Node):
    """One ROS 2 node (``name``, absolute: ``/vehicle_1/openconvoy_link`` is node
    ``openconvoy_link`` in namespace ``/vehicle_1``) in a subprocess of the ROS 2
    environment; the methods of ``Ros1Node`` (``subscribe``'s ``nodelay``/``any_md5`` mean
    nothing here: each topic gets MAVROS 2's QoS, ``qos_for``). ``netns_pid``: join that
    process's network namespace (default ``OPENCONVOY_ROS2_NETNS``; none: this one's).
    ``discovery``: the node's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (default: the environment's,
    else ``LOCALHOST``)."""

    ROS = "ROS 2"

    def __init__(
        self,
        name: str,
        timeout_s: float = 60.0,
        msg_dir: Path = MSG_DIR,
        netns_pid: int | None = None,
        discovery: str | None = None,
    ) -> None:
        env_pid = os.environ.get(NETNS_ENV)
        self.netns_pid = netns_pid if netns_pid is not None else (int(env_pid) if env_pid else None)
        self.discovery = discovery
        super().__init__(name, None, timeout_s, msg_dir)

    def _agent(
        self, name: str, master_uri: str | None, msg_dir: Path
    ) -> tuple[list[str], dict[str, str]]:
        prefixes = [build_mavros_msgs(msg_dir)]
        prefixes += [build_interfaces(p) for p in ("ardupilot_msgs", "openconvoy_msgs")]
        argv = [str(ros2_python()), str(AGENT), "/" + name.lstrip("/")]
        if self.netns_pid is not None:
            enter = ["nsenter", "--preserve-credentials", "-U", "-n", "-t", str(self.netns_pid)]
            argv = enter + argv
        env = ros2_env(prefixes)
        if self.discovery is not None:
            env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = self.discovery
        return argv, env

    def subscribe(
        self,
        topic: str,
        type_name: str,
        callback: object,
        nodelay: bool = False,
        any_md5: bool = False,
    ) -> None:
        """Call ``callback(msg_dict)`` for each message on ``topic`` (``pkg/Type``)."""
        self._subs.setdefault(topic, []).append(callback)  # type: ignore[arg-type]
        self._send({"op": "sub", "topic": topic, "type": type_name, "qos": qos_for(topic)})

    def advertise(self, topic: str, type_name: str, latch: bool = False) -> None:
        qos = "state" if latch else qos_for(topic)
        self._send({"op": "adv", "topic": topic, "type": type_name, "qos": qos})

    def publishers(self, topic: str, timeout_s: float = 10.0) -> list[dict[str, str]]:
        """The publishers of ``topic`` this node has discovered: node, type, RIHS01 type
        hash, reliability, durability."""
        return list(self._request({"op": "publishers", "topic": topic}, timeout_s)["publishers"])


class CycloneNode(Ros2Node):
    """A ``Ros2Node`` without ROS: the same methods (``sub``/``adv``/``pub``/``call`` of the
    ``ap-dds`` link's types) through Cyclone DDS directly (``cyclone_agent.py``, run by this
    Python: no ROS 2 environment needed). ``iface``: keep Cyclone on that interface
    (``OPENCONVOY_DDS_IFACE``; default: Cyclone's own configuration); ``domain_id``: the
    DDS domain (default ``ROS_DOMAIN_ID``, else 0)."""

    ROS = "DDS (Cyclone)"

    def __init__(
        self,
        name: str,
        timeout_s: float = 30.0,
        netns_pid: int | None = None,
        iface: str | None = None,
        domain_id: int | None = None,
    ) -> None:
        self.iface, self.domain_id = iface, domain_id
        super().__init__(name, timeout_s, MSG_DIR, netns_pid)

    def _agent(
        self, name: str, master_uri: str | None, msg_dir: Path
    ) -> tuple[list[str], dict[str, str]]:
        try:
            import cyclonedds  # noqa: F401
        except ModuleNotFoundError:
            raise DependencyMissing(
                "--link ap-dds needs Cyclone DDS: pip install 'openconvoy[px4dds]'"
            ) from None
        argv = [sys.executable, "-m", "openconvoy.bridge.ros.cyclone_agent", "/" + name.lstrip("/")]
        if self.netns_pid is not None:
            enter = ["nsenter", "--preserve-credentials", "-U", "-n", "-t", str(self.netns_pid)]
            argv = enter + argv
        env = dict(os.environ)
        if self.iface:
            env["OPENCONVOY_DDS_IFACE"] = self.iface
        if self.domain_id is not None:
            env["ROS_DOMAIN_ID"] = str(self.domain_id)
        return argv, env


class LoopbackNetns:
    """A private network namespace with only loopback up (``unshare -rn``), held open by a
    process whose pid ROS 2 nodes join (``Ros2Node(netns_pid=...)``): DDS discovery
    then reaches nothing beyond it. ``veth``: also the veth pair of ``comms.netns``
    (``oc0``, multicast-capable: where Fast DDS and Cyclone DDS find each other).
    ``close`` ends it."""

    def __init__(self, veth: bool = False) -> None:
        from openconvoy.comms.netns import netns_unavailable_reason

        why = netns_unavailable_reason()
        if why:
            raise DependencyMissing(why)
        wire = "ip link set lo up"
        if veth:
            wire = (
                f"{sys.executable} -c 'from openconvoy.comms import netns; netns.setup_network()'"
            )
        self._proc = subprocess.Popen(
            ["unshare", "-rn", "sh", "-c", f"{wire} && echo up && exec cat"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self._proc.stdout is not None
        if self._proc.stdout.readline().strip() != "up":
            self.close()
            raise LinkError("could not set up a private network namespace")
        self.pid = self._proc.pid

    def close(self) -> None:
        if self._proc.poll() is None:
            assert self._proc.stdin is not None
            self._proc.stdin.close()
            try:
                self._proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()

    def __enter__(self) -> LoopbackNetns:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def type_hashes(
    msg_dir: Path, timeout_s: float = 120.0, pkg: str = "mavros_msgs"
) -> dict[str, str]:
    """The RIHS01 type hashes rosidl gives the interfaces in ``msg_dir`` (``msg/*.msg``,
    ``srv/*.srv``) as package ``pkg`` (default ``mavros_msgs``): ``{"mavros_msgs/msg/State": "RIHS01_..."}``,
    computed by the ROS 2 environment's ``rosidl_adapter`` and
    ``rosidl_generator_type_description`` (what ``rosidl_generate_interfaces`` runs)."""
    why = ros2_available()
    if why:
        raise DependencyMissing(why)
    msg_dir = msg_dir.resolve()
    r = subprocess.run(
        [
            str(ros2_python()),
            "-c",
            _HASH_SCRIPT,
            str(msg_dir),
            str(ros2_venv() / "share"),
            pkg,
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=ros2_env(None),
    )
    if r.returncode != 0:
        raise LinkError(f"type hashes of {msg_dir}: {r.stderr.strip().splitlines()[-1:]}")
    return dict(json.loads(r.stdout.strip().splitlines()[-1]))


_HASH_SCRIPT = """
import json, sys, tempfile
from pathlib import Path
from rosidl_adapter import convert_to_idl
from rosidl_generator_type_description import generate_type_hash
msg_dir, share, pkg = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
tmp = Path(tempfile.mkdtemp())
tuples = []
for f in sorted(msg_dir.glob("msg/*.msg")) + sorted(msg_dir.glob("srv/*.srv")):
    idl = convert_to_idl(msg_dir, pkg, f.relative_to(msg_dir), tmp / "idl")
    tuples.append(f"{tmp / 'idl'}:{idl.relative_to(tmp / 'idl')}")
args = {
    "package_name": pkg, "output_dir": str(tmp / "out"), "idl_tuples": tuples,
    "include_paths": [f"{p}:{share / p}" for p in
                      ("std_msgs", "geometry_msgs", "builtin_interfaces", "service_msgs")],
}
(tmp / "args.json").write_text(json.dumps(args))
out = {}
for path in generate_type_hash(str(tmp / "args.json")):
    d = json.loads(Path(path).read_text())
    out[d["type_hashes"][0]["type_name"]] = d["type_hashes"][0]["hash_string"]
print(json.dumps(out))
"""


def main() -> int:
    """``python -m openconvoy.bridge.ros.ros2 --build``: build our ``mavros_msgs`` now
    (``make ros2`` does, so that tests and the first node do not wait for it)."""
    if sys.argv[1:] != ["--build"]:
        print("usage: python -m openconvoy.bridge.ros.ros2 --build", file=sys.stderr)
        return 2
    try:
        print(build_mavros_msgs())
        print(build_interfaces("ardupilot_msgs"))
        print(build_interfaces("openconvoy_msgs"))
    except (LinkError, DependencyMissing) as exc:
        print(exc, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
