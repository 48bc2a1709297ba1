"""D67 (defects-aea1a73.md): values that used to be accepted silently are one line, exit 2:
a fault after the run ends, a run shorter than a control period, a replay window that
rejects everything, a log whose vehicle ids or times are impossible."""

from __future__ import annotations

from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.convoy import load_convoy
from openconvoy.core.errors import ConfigError, InputFileError
from openconvoy.envs import ConvoyEnv
from openconvoy.logs import COLUMNS, read_log


def _one_error(capsys) -> str:
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1, err
    return err[0]


def test_a_fault_after_the_run_ends_is_refused(tmp_path: Path, capsys) -> None:
    argv = ["sim", "--fault", "silent:1@1e300", "--duration", "2", "--no-plots"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 2
    assert "after the run ends at 2 s (it would never happen)" in _one_error(capsys)
    exp = tmp_path / "e.toml"
    exp.write_text(
        '[experiment]\nfaults = ["halt:0@1e9"]\npers = [0.0]\nseeds = 1\nduration_s = 2.0\n'
    )
    assert (
        main(["experiment", "per-sweep", "--config", str(exp), "--out", str(tmp_path / "c")]) == 2
    )
    assert _one_error(capsys).startswith("openconvoy: error: fault halt:0@1e+09: at 1e+09 s")
    assert not (tmp_path / "c").exists()
    with pytest.raises(ConfigError, match="after the run ends"):
        ConvoyEnv(faults=["dead:1@100"], max_time_s=10.0)


def test_a_run_shorter_than_a_control_period_is_refused(tmp_path: Path, capsys) -> None:
    assert main(["sim", "--duration", "1e-9", "--out", str(tmp_path / "b")]) == 2
    assert "--duration: 1e-9 is out of range" in _one_error(capsys)


def test_a_replay_window_that_rejects_everything_is_refused(tmp_path: Path) -> None:
    convoy = tmp_path / "c.toml"
    convoy.write_text('[convoy]\nname = "d"\n[v2v]\nreplay_window_s = 1e-9\n')
    with pytest.raises(ConfigError, match=r"v2v.replay_window_s: 1e-09 is out of range"):
        load_convoy(convoy)


def _log(tmp_path: Path, rows: list[tuple[float, int]]) -> Path:
    """A log in ``openconvoy.logs``' columns, one row per ``(t_s, vehicle_id)``."""
    path = tmp_path / "log.csv"
    lines = [",".join(COLUMNS)]
    for t, v in rows:
        values = {c: "0.0" for c in COLUMNS} | {"t_s": str(t), "vehicle_id": str(v)}
        values["mode"] = "coop"
        lines.append(",".join(values[c] for c in COLUMNS))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([(0.0, 0), (0.05, 0), (0.1, 0), (0.075, 0)], "vehicle 0's time goes back to 0.075 s"),
        ([(0.0, -1), (0.05, -1)], "column vehicle_id: -1"),
        ([(0.0, 1_000_000_000)], "column vehicle_id: 1000000000"),
    ],
)
def test_a_log_with_impossible_ids_or_times_is_one_line(tmp_path: Path, rows, message) -> None:
    with pytest.raises(InputFileError, match=message):
        read_log(_log(tmp_path, rows))
