"""The run recorder: the CSV in the simulator's columns plus extras, and the metadata JSON."""

from __future__ import annotations

import json
import math

from openconvoy.bridge.recorder import RunRecorder
from openconvoy.logs import COLUMNS, read_log


def _row(t: float) -> dict:
    row = dict.fromkeys(COLUMNS, 0.0)
    row.update(
        t_s=t,
        vehicle_id=2,
        mode="coop",
        msgs_sent=1,
        msgs_received=0,
        msgs_lost=0,
        gap_m=math.nan,
        x_m=t,
    )
    return {**row, "length_m": 0.8}


def test_rows_then_metadata_and_nothing_without_a_directory(tmp_path) -> None:
    rec = RunRecorder(tmp_path, 2, ("length_m",))
    assert not rec.recording
    rec.open()
    assert rec.recording
    for k in range(3):
        rec.row(_row(0.05 * k))
    rec.close({"kind": "deploy", "exit_code": 0})
    rec.close({"kind": "again"})  # once only
    log = read_log(tmp_path / "vehicle_2.csv")
    assert log["x_m"].tolist() == [0.0, 0.05, 0.1] and log["length_m"].tolist() == [0.8] * 3
    assert json.loads((tmp_path / "vehicle_2.json").read_text()) == {
        "kind": "deploy",
        "exit_code": 0,
    }
    nothing = RunRecorder(None, 1)
    nothing.open()
    nothing.row(_row(0.0))
    nothing.close({"kind": "deploy"})
    assert not nothing.recording and sorted(p.name for p in tmp_path.iterdir()) == [
        "vehicle_2.csv",
        "vehicle_2.json",
    ]
