"""Runs as ROS 2 bags (``openconvoy.bag``): ``sim --bag`` writes one; two independent readers
(rosbags, through ``read_log``, and ``mcap_ros2``, the MCAP project's ROS 2 decoder) give
back the values of ``log.csv``; ``report`` and ``compare`` read it as they read the CSV."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from openconvoy.bag import MSG_DIR, BagWriter, read_bag, status_log
from openconvoy.cli import main
from openconvoy.logs import COLUMNS, read_log


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "run"
    rc = main(
        ["sim", "--duration", "6", "--per", "0.2", "--seed", "3", "--bag", "--out", str(out)]
        + ["--quiet", "--no-plots"]
    )
    assert rc == 0
    return out


def _decoded(bag: Path) -> dict[str, list]:
    """Every message of the bag's MCAP file, decoded by mcap_ros2, by topic."""
    (mcap_file,) = bag.glob("*.mcap")
    out: dict[str, list] = {}
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, msg in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, msg))
    return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype == object:
        return list(a) == list(b)
    return bool(np.array_equal(a, b, equal_nan=True))


def test_our_message_carries_every_log_column() -> None:
    fields = [
        line.split()[1]
        for line in (MSG_DIR / "ConvoyStatus.msg").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    assert fields[0] == "header"
    assert fields[1 : 1 + len(COLUMNS)] == list(COLUMNS)


def test_rosbags_reads_back_log_csv(run: Path) -> None:
    csv_log = read_log(run / "log.csv")
    bag_log = read_log(run / "bag")  # read_log dispatches to read_bag (rosbags)
    assert list(bag_log) == list(csv_log)  # DESIGN's columns, then length_m
    assert "length_m" in bag_log
    assert len(bag_log["t_s"]) == len(csv_log["t_s"]) == 3 * 121  # 3 vehicles, 0..6 s at 20 Hz
    for c in csv_log:
        assert _same(bag_log[c], csv_log[c]), c
    assert csv_log["msgs_lost"].max() > 0  # PER 0.2 bites
    # Cooperative throughout, but for a follower's first ticks before it has heard the car
    # ahead (``core.safety.verdict``'s BLIND: mode ``stop``, at rest at the start).
    modes, t = csv_log["mode"], csv_log["t_s"]
    assert set(modes) <= {"coop", "stop"} and np.all(t[modes == "stop"] < 0.5)
    assert np.all(csv_log["speed_mps"][modes == "stop"] == 0.0)


def test_mcap_ros2_reads_the_same_values(run: Path) -> None:
    csv_log = read_log(run / "log.csv")
    topics = _decoded(run / "bag")
    assert {t for t in topics if t.startswith("/vehicle_1/")} == {
        "/vehicle_1/status",
        "/vehicle_1/fix",
        "/vehicle_1/odom",
        "/vehicle_1/cmd",
    }
    status = [m for t in sorted(topics) if t.endswith("/status") for _, m in topics[t]]
    via_mcap = status_log(status)
    for c in csv_log:
        assert _same(via_mcap[c], csv_log[c]), c
    sel = csv_log["vehicle_id"] == 2
    fix = topics["/vehicle_2/fix"]
    odom = [m for _, m in topics["/vehicle_2/odom"]]
    cmd = [m for _, m in topics["/vehicle_2/cmd"]]
    assert [t for t, _ in fix] == [round(t * 1e9) for t in csv_log["t_s"][sel]]
    assert _same(np.array([m.latitude for _, m in fix]), csv_log["lat_deg"][sel])
    assert _same(np.array([m.longitude for _, m in fix]), csv_log["lon_deg"][sel])
    assert _same(np.array([m.pose.pose.position.x for m in odom]), csv_log["x_m"][sel])
    assert _same(np.array([m.pose.pose.position.y for m in odom]), csv_log["y_m"][sel])
    yaw = [2 * math.atan2(m.pose.pose.orientation.z, m.pose.pose.orientation.w) for m in odom]
    assert np.allclose(yaw, csv_log["heading_rad"][sel], atol=1e-12)
    assert _same(np.array([m.twist.twist.linear.x for m in odom]), csv_log["speed_mps"][sel])
    assert _same(np.array([m.twist.linear.x for m in cmd]), csv_log["cmd_speed_mps"][sel])
    assert np.allclose(
        [m.twist.angular.z * 0.05 for m in cmd],
        csv_log["cmd_heading_change_rad"][sel],
        equal_nan=True,
    )
    assert odom[0].header.frame_id == "map" and odom[0].child_frame_id == "vehicle_2/base_link"


def test_report_and_compare_read_the_bag_as_the_csv(run: Path, capsys) -> None:
    assert main(["report", str(run / "log.csv"), "--out", str(run / "m_csv.json")]) == 0
    assert main(["report", str(run / "bag"), "--out", str(run / "m_bag.json")]) == 0
    a = json.loads((run / "m_csv.json").read_text())
    b = json.loads((run / "m_bag.json").read_text())
    assert a == b and a["p95_platooning_error_m"] > 0
    cmp = run / "cmp.json"
    assert main(["compare", str(run / "log.csv"), str(run / "bag"), "--out", str(cmp)]) == 0
    diffs = json.loads(cmp.read_text())["metrics"]
    assert diffs["p95_platooning_error_m"]["b"] == a["p95_platooning_error_m"]
    assert all(v["diff"] == 0 for v in diffs.values() if v["diff"] is not None), diffs


def test_report_writes_metrics_beside_a_bag_not_into_it(run: Path) -> None:
    assert main(["report", str(run / "bag")]) == 0
    assert not (run / "bag" / "metrics.json").exists()
    assert json.loads((run / "metrics.json").read_text())["collisions"] == 0


def test_sim_never_deletes_a_bag_directory_that_is_not_a_bag(tmp_path: Path, capsys) -> None:
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "notes.txt").write_text("mine")
    argv = ["sim", "--duration", "1", "--bag", "--out", str(tmp_path), "--quiet", "--no-plots"]
    assert main(argv) == 2
    assert "is not a ROS 2 bag" in capsys.readouterr().err
    assert (tmp_path / "bag" / "notes.txt").read_text() == "mine"


def test_v2v_bytes_round_trip(tmp_path: Path) -> None:
    frames = [bytes(range(7)), b"\x00\x14" + bytes(range(200, 256))]
    with BagWriter(tmp_path / "b", tick_s=0.05) as bag:
        bag.v2v(1.5, 2, "tx", frames[0])
        bag.v2v(1.75, 2, "rx", frames[1])
        with pytest.raises(ValueError, match="direction"):
            bag.v2v(2.0, 2, "sideways", b"")
    topics = _decoded(tmp_path / "b")
    assert [bytes(m.data) for _, m in topics["/vehicle_2/v2v/tx"]] == frames[:1]
    assert [(t, bytes(m.data)) for t, m in topics["/vehicle_2/v2v/rx"]] == [
        (1_750_000_000, frames[1])
    ]


def test_a_bag_without_a_log_is_one_error_line(tmp_path: Path, capsys) -> None:
    with BagWriter(tmp_path / "b", tick_s=0.05) as bag:
        bag.v2v(0.0, 0, "tx", b"x")
    assert main(["report", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("openconvoy: error:") and "ConvoyStatus" in err and "\n" not in err
    (tmp_path / "b" / "b.mcap").write_bytes(b"not an mcap file")
    with pytest.raises(Exception, match="not a readable ROS 2 bag"):
        read_bag(tmp_path / "b")
