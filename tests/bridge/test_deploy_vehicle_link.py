"""``deploy`` without ``--link`` takes its vehicle's link from the convoy file's
``[[vehicle]]`` tables; ``--link`` given, the command line decides; a bad table is one line
and exit 2 before anything opens."""

from __future__ import annotations

import socket

from openconvoy.bridge.deploy import DeployArgs, _link_name, with_vehicle_link
from openconvoy.cli import main
from openconvoy.convoy import load_convoy
from openconvoy.testing import free_port

TABLES = (
    '[convoy]\nname = "t"\nvehicles = ["1/10", "1/6", "1/10"]\n[v2v]\nauth = "off"\n'
    '[[vehicle]]\nlink = "mavlink"\n'
    '[[vehicle]]\nlink = "mavros"\nros = 2\nnamespace = "/vehicle_1/mavros"\n'
    '[[vehicle]]\nlink = "px4-dds"\nnamespace = "vehicle_2"\ndds_domain = 7\n'
)


def _args(path: str, vehicle_id: int, **kw: object) -> DeployArgs:
    return DeployArgs(
        policy="paper", vehicle_id=vehicle_id, convoy=path, mavlink=None, iface="oc0", **kw
    )  # type: ignore[arg-type]


def test_each_vehicle_gets_its_tables_link_unless_link_is_given(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(TABLES)
    convoy = load_convoy(path)
    names = [_link_name(with_vehicle_link(_args(str(path), i), convoy)) for i in range(3)]
    assert names == [
        "mavlink",
        "mavros (ROS 2, /vehicle_1/mavros)",
        "px4-dds (domain 7, ns vehicle_2)",
    ]
    given = with_vehicle_link(_args(str(path), 1, link="ap-dds", ap_ns="/x/ap"), convoy)
    assert _link_name(given) == "ap-dds (DDS domain 0, /x/ap)"  # the command line wins
    path.write_text(TABLES.split("[[vehicle]]")[0])  # no tables: MAVLink
    assert with_vehicle_link(_args(str(path), 1), load_convoy(path)).link == "mavlink"


def _deploy(path, vehicle_id: int, *extra: str) -> list[str]:
    return [
        "deploy", "--policy", "paper", "--vehicle-id", str(vehicle_id), "--convoy", str(path),
        "--iface", "oc0", *extra,
    ]  # fmt: skip


def test_a_bad_table_is_one_line_and_exit_2(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(TABLES.replace('link = "mavros"', 'link = "mavros2"'))
    url = f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    assert main(_deploy(path, 0, "--mavlink", url)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "vehicle[1].link" in err[0] and "'mavros2'" in err[0], err


def test_a_mavlink_vehicle_from_the_file_still_needs_its_url(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(TABLES)
    assert main(_deploy(path, 0)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--mavlink URL is required" in err[0], err
