"""Our px4_msgs types (``bridge.px4dds.msgs``) field by field against px4_msgs' own .msg text
(``tests/data/px4_msgs/``, px4_msgs main a4a9864b): same names, same order, same types,
same constants, and the ROS 2 DDS type names a px4_msgs node announces."""

from __future__ import annotations

import re
import typing
from pathlib import Path

import pytest
from cyclonedds.idl import types as t

from openconvoy.bridge.px4dds import msgs

DATA = Path(__file__).resolve().parents[1] / "data" / "px4_msgs"

SCALARS: dict[str, object] = {
    "bool": bool,
    "uint8": t.uint8,
    "uint16": t.uint16,
    "uint32": t.uint32,
    "uint64": t.uint64,
    "int8": t.int8,
    "int16": t.int16,
    "int32": t.int32,
    "int64": t.int64,
    "float32": t.float32,
    "float64": t.float64,
}


def msg_fields(text: str) -> list[tuple[str, object]]:
    """(name, cyclonedds type) of each field of a ROS .msg text, in order (constants out)."""
    fields = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or "=" in line:
            continue
        typ, name = line.split()
        m = re.fullmatch(r"(\w+)\[(\d+)\]", typ)
        fields.append((name, t.array[SCALARS[m[1]], int(m[2])] if m else SCALARS[typ]))
    return fields


def msg_constants(text: str) -> dict[str, int]:
    out = {}
    for line in text.splitlines():
        m = re.match(r"\s*\w+\s+(\w+)\s*=\s*(-?\d+)", line.split("#", 1)[0])
        if m:
            out[m[1]] = int(m[2])
    return out


@pytest.mark.parametrize("cls", msgs.ALL, ids=lambda c: c.__name__)
def test_fields_equal_px4_msgs(cls: type) -> None:
    text = (DATA / f"{cls.__name__}.msg").read_text()
    hints = typing.get_type_hints(cls, include_extras=True)
    ours = [(n, h) for n, h in hints.items() if not n.startswith("_")]
    assert ours == msg_fields(text)
    assert msg_constants(text).get("MESSAGE_VERSION", 0) == msgs.VERSIONS[cls.__name__]
    assert cls.__idl__.idl_transformed_typename == f"px4_msgs::msg::dds_::{cls.__name__}_"


def test_topic_names_as_px4_makes_them() -> None:
    """utilities.hpp's ``rt/<ns>/fmu/<dir>/<name>``, ``_vN`` for versioned messages."""
    from openconvoy.bridge.px4dds.dds import topic_name

    assert topic_name("", "in", msgs.TrajectorySetpoint) == "rt/fmu/in/trajectory_setpoint"
    assert topic_name("vehicle_2", "in", msgs.OffboardControlMode) == (
        "rt/vehicle_2/fmu/in/offboard_control_mode"
    )
    assert topic_name("/v1/", "out", msgs.VehicleStatus) == "rt/v1/fmu/out/vehicle_status_v4"
    assert topic_name("", "out", msgs.VehicleLocalPosition) == (
        "rt/fmu/out/vehicle_local_position_v1"
    )
    assert topic_name("", "out", msgs.VehicleGlobalPosition) == "rt/fmu/out/vehicle_global_position"


def test_constants_equal_px4_msgs() -> None:
    status = msg_constants((DATA / "VehicleStatus.msg").read_text())
    cmd = msg_constants((DATA / "VehicleCommand.msg").read_text())
    ack = msg_constants((DATA / "VehicleCommandAck.msg").read_text())
    ours = {
        n: v for n, v in vars(msgs).items() if n.isupper() and type(v) is int and n != "VERSIONS"
    }
    assert ours, "no constants"
    for name, value in ours.items():
        assert {**status, **cmd, **ack}[name] == value, name


def test_xcdr1_sizes() -> None:
    """XCDR1 of a default VehicleStatus / TrajectorySetpoint: 4-byte encapsulation header +
    fields with natural alignment, as px4_msgs' generated C++ serializes them."""
    assert msgs.TrajectorySetpoint().serialize()[:4] == b"\x00\x01\x00\x00"  # CDR_LE
    assert len(msgs.TrajectorySetpoint().serialize()) == 4 + 8 + 4 * 3 * 4 + 4 + 4
    assert len(msgs.OffboardControlMode().serialize()) == 4 + 8 + 7
