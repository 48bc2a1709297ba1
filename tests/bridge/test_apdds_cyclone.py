"""The ``ap-dds`` link without ROS: its node is Cyclone DDS directly (``CycloneNode``,
``cyclone_agent.py``, our DDS types in ``apdds_msgs``), talking to the AP_DDS stand-in that
runs on real rclpy (PyPI's Jazzy wheels, Fast DDS) — two DDS implementations on the veth
of a private network namespace, topics and services (``rq/…Request``, ``rr/…Reply``)."""

from __future__ import annotations

import json
import math
import re
import subprocess
from collections.abc import Iterator
from dataclasses import fields
from pathlib import Path

import pytest

from openconvoy.bridge.ros import apdds_msgs as am
from openconvoy.bridge.ros.apdds_link import ApDdsLink
from openconvoy.bridge.ros.apdds_standin import ApDdsStandIn
from openconvoy.bridge.ros.cyclone_agent import service_topics
from openconvoy.bridge.ros.ros2 import (
    CycloneNode,
    LoopbackNetns,
    Ros2Node,
    build_interfaces,
    ros2_env,
    ros2_python,
)
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.comms.dds import V2VBytes
from openconvoy.comms.netns import IFACE
from openconvoy.testing import drive_on_heading, free_port, wait_for

ARDUPILOT_MSGS = Path(__file__).resolve().parents[1] / "data" / "ros" / "ardupilot-msgs"
IDL = {
    "int8": "int8", "uint8": "uint8", "uint16": "uint16", "int32": "int32", "uint32": "uint32",
    "float64": "double", "bool": "boolean", "str": "string",
}  # fmt: skip


def _ours(cls: type) -> dict[str, str]:
    """Our DDS type's fields in rclpy's notation (``double``, ``sequence<uint8>``,
    ``double[9]``, ``pkg/Type``)."""
    out = {}
    for f in fields(cls):
        if isinstance(f.type, type) and issubclass(f.type, am.IdlStruct):
            pkg = f.type.__idl_typename__.split("::")[0]
            out[f.name] = f"{pkg}/{f.type.__name__}"
        elif "sequence" in repr(f.type):
            out[f.name] = "sequence<uint8>"
        elif "array" in repr(f.type):
            out[f.name] = "double[9]"
        elif f.type is bool:
            out[f.name] = "boolean"
        elif f.type is str:
            out[f.name] = "string"
        else:
            out[f.name] = IDL[re.sub(r".*\b(u?int\d+|float64)\b.*", r"\1", repr(f.type))]
    return out


CLASSES = {
    "builtin_interfaces/Time": am.Time, "std_msgs/Header": am.Header,
    "sensor_msgs/NavSatStatus": am.NavSatStatus, "sensor_msgs/NavSatFix": am.NavSatFix,
    "geometry_msgs/Point": am.Point, "geometry_msgs/Quaternion": am.Quaternion,
    "geometry_msgs/Pose": am.Pose, "geometry_msgs/PoseStamped": am.PoseStamped,
    "geometry_msgs/Vector3": am.Vector3, "geometry_msgs/Twist": am.Twist,
    "geometry_msgs/TwistStamped": am.TwistStamped, "ardupilot_msgs/Status": am.Status,
    "ardupilot_msgs/srv/ArmMotors_Request": am.ArmMotors_Request,
    "ardupilot_msgs/srv/ArmMotors_Response": am.ArmMotors_Response,
    "ardupilot_msgs/srv/ModeSwitch_Request": am.ModeSwitch_Request,
    "ardupilot_msgs/srv/ModeSwitch_Response": am.ModeSwitch_Response,
    "openconvoy_msgs/V2VBytes": V2VBytes,  # V2V over ROS 2 (comms.dds)
}  # fmt: skip

_RCLPY_FIELDS = """
import importlib, json, sys
out = {}
for name in json.loads(sys.argv[1]):
    parts = name.split("/")
    if parts[1] == "srv":
        srv, kind = parts[2].rsplit("_", 1)
        cls = getattr(getattr(importlib.import_module(parts[0] + ".srv"), srv), kind)
    else:
        cls = getattr(importlib.import_module(parts[0] + ".msg"), parts[1])
    out[name] = cls.get_fields_and_field_types()
print(json.dumps(out))
"""


def test_our_dds_types_are_rclpys_field_for_field_and_ardupilots() -> None:
    """Each DDS type we wrote has the fields, in order and of the types, that rclpy's
    generated class of the same interface has (ROS 2 Jazzy; ``ardupilot_msgs`` built by
    rosidl from ArduPilot's text, ``openconvoy_msgs`` from ours), and our ardupilot_msgs fields are those of ArduPilot's
    .msg/.srv files."""
    r = subprocess.run(
        [str(ros2_python()), "-c", _RCLPY_FIELDS, json.dumps(sorted(CLASSES))],
        capture_output=True,
        text=True,
        timeout=120,
        env=ros2_env([build_interfaces(p) for p in ("ardupilot_msgs", "openconvoy_msgs")]),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    theirs = json.loads(r.stdout.strip().splitlines()[-1])
    for name, cls in CLASSES.items():
        ours = _ours(cls)
        want = {k: v.replace("/msg/", "/") for k, v in theirs[name].items()}
        assert list(ours.items()) == list(want.items()), name
        dds = cls.__idl_typename__  # type: ignore[attr-defined]
        pkg, kind = name.split("/")[0], "srv" if "/srv/" in name else "msg"
        assert dds == f"{pkg}::{kind}::dds_::{name.split('/')[-1]}_"
    # ArduPilot's own text: Status.msg, ArmMotors.srv, ModeSwitch.srv
    for path, parts in (
        ("msg/Status.msg", [am.Status]),
        ("srv/ArmMotors.srv", [am.ArmMotors_Request, am.ArmMotors_Response]),
        ("srv/ModeSwitch.srv", [am.ModeSwitch_Request, am.ModeSwitch_Response]),
    ):
        sections = (ARDUPILOT_MSGS / path).read_text().split("\n---")
        for text, cls in zip(sections, parts, strict=True):
            declared = [
                line.split()[:2]
                for line in (ln.split("#")[0].strip() for ln in text.splitlines())
                if line and "=" not in line
            ]
            assert [n for _, n in declared] == [f.name for f in fields(cls)], path


def test_service_names_map_as_rmw_and_ap_dds_name_them() -> None:
    assert service_topics("/ap/arm_motors") == ("rq/ap/arm_motorsRequest", "rr/ap/arm_motorsReply")
    assert service_topics("/vehicle_1/ap/mode_switch")[0] == "rq/vehicle_1/ap/mode_switchRequest"
    fix = am.from_dict(
        am.NavSatFix, {"header": {"stamp": 12.25, "frame_id": "GPS_0"}, "latitude": 1.5}
    )
    assert (fix.header.stamp.sec, fix.header.stamp.nanosec) == (12, 250_000_000)
    assert am.to_dict(fix)["header"] == {"stamp": 12.25, "frame_id": "GPS_0"}


@pytest.fixture(scope="module")
def veth_netns(monkeypatch_module) -> Iterator[LoopbackNetns]:
    # A lab's ROS 2 nodes find their peers on the network: here the namespace's veth.
    monkeypatch_module.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    with LoopbackNetns(veth=True) as ns:
        yield ns


@pytest.fixture(scope="module")
def monkeypatch_module() -> Iterator[pytest.MonkeyPatch]:
    with pytest.MonkeyPatch.context() as mp:
        yield mp


@pytest.mark.e2e
def test_cyclone_link_drives_the_vehicle_through_the_rclpy_stand_in(veth_netns) -> None:
    """Connects (status, navsat, pose, twist from rclpy), switches mode and arms through
    AP_DDS's services, commanded west the rover turns round and drives with x decreasing;
    the stand-in forwarded our cmd_vel and dropped none."""
    port = free_port()
    vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", SimVehicleConfig(ready_after_s=0.0)).start()
    standin = ApDdsStandIn(
        Ros2Node("/ap_standin", netns_pid=veth_netns.pid), f"udpout:127.0.0.1:{port}", "/v5/ap"
    ).start()
    link = ApDdsLink(
        lambda: CycloneNode("/ap_link", netns_pid=veth_netns.pid, iface=IFACE), "/v5/ap",
        DEFAULT_HOME, 5,
    )  # fmt: skip
    try:
        link.connect(30.0)
        link.modes.prepare_and_arm(30.0)
        driving_west, xs = drive_on_heading(link, math.pi)  # west
        x0 = xs[-1]
        assert wait_for(lambda: driving_west() and xs[-1] < x0 - 1.0, 5.0)
        assert vehicle.state().speed > 1.0
        assert standin.setpoints_forwarded > 10 and standin.commands_dropped == 0
        link.modes.hold(3.0)  # mode_switch again: HOLD, confirmed on /ap/status
        modes: list[str] = []
        assert wait_for(
            lambda: bool(t := link.poll()) and modes.append(t.mode) is None and modes[-1] == "HOLD",
            5.0,
        )
    finally:
        link.close()
        standin.stop()
        standin.node.close()
        vehicle.stop()
