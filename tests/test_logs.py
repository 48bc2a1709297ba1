import math

import numpy as np
import pytest

from openconvoy.logs import COLUMNS, LogWriter, read_log


def _row(t: float, vid: int, **kw):
    row = {c: 0.0 for c in COLUMNS}
    row.update(t_s=t, vehicle_id=vid, mode="coop", msgs_sent=3, msgs_received=2, msgs_lost=1)
    row.update(kw)
    return row


def test_roundtrip_and_missing_values(tmp_path):
    path = tmp_path / "log.csv"
    with LogWriter(path, extra_columns=["extra"]) as log:
        log.write(_row(0.0, 0, gap_m=None, extra=1.5))
        log.write(_row(0.05, 1, gap_m=14.25, mode="degraded"))
    data = read_log(path)
    assert list(data)[: len(COLUMNS)] == list(COLUMNS)
    assert math.isnan(data["gap_m"][0]) and data["gap_m"][1] == 14.25
    assert list(data["mode"]) == ["coop", "degraded"]
    assert data["msgs_sent"].dtype == np.int64 and data["extra"][0] == 1.5


def test_directory_of_vehicle_logs_merges_on_time(tmp_path):
    for vid in (0, 1, 2):
        with LogWriter(tmp_path / f"vehicle_{vid}.csv") as log:
            for k in range(3):
                log.write(_row(k * 0.05 + vid * 0.001, vid))
    (tmp_path / "notes.csv").write_text("a,b\n1,2\n")  # not a log: ignored
    data = read_log(tmp_path)
    assert len(data["t_s"]) == 9
    assert np.all(np.diff(data["t_s"]) >= 0)
    assert list(data["vehicle_id"][:3]) == [0, 1, 2]


def test_rows_survive_without_close(tmp_path):
    path = tmp_path / "log.csv"
    log = LogWriter(path)
    log.write(_row(0.0, 0))
    # Not closed (as after SIGKILL of a later tick): the row is already on disk.
    assert len(read_log(path)["t_s"]) == 1


def test_unknown_column_and_bad_file_are_clear_errors(tmp_path):
    with LogWriter(tmp_path / "log.csv") as log, pytest.raises(KeyError, match="nope"):
        log.write({"nope": 1})
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,vehicle_id\n0,0\n")
    with pytest.raises(ValueError, match="missing column"):
        read_log(bad)
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "absent")
