"""The ``sim``, ``report``, ``presets`` and ``compare`` commands, end to end in-process."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.core.config import load_toml
from openconvoy.core.metrics import METRIC_KEYS
from openconvoy.envs.vehicles import VEHICLE_PRESETS
from openconvoy.experiments.runs import LossSection, RunConfig
from openconvoy.policies.presets import PRESETS


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "paper"
    rc = main(
        [
            "sim",
            "--scenario",
            "paper",
            "--policy",
            "paper",
            "--per",
            "0",
            "--seed",
            "0",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert rc == 0
    return out


def test_sim_writes_log_metrics_and_plots(paper_run: Path):
    for name in (
        "log.csv",
        "metrics.json",
        "run.toml",
        "trajectories.png",
        "gaps.png",
        "speeds.png",
    ):
        assert (paper_run / name).stat().st_size > 0, name
    metrics = json.loads((paper_run / "metrics.json").read_text())
    assert set(METRIC_KEYS) <= set(metrics)
    # Issue 2, through the CLI: the paper's controller at PER 0.
    assert metrics["p95_platooning_error_m"] < 1.0
    assert metrics["collisions"] == 0
    assert metrics["delivery_ratio"] == 1.0
    assert set(metrics["per_follower"]) == {"1", "2"}
    with (paper_run / "log.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 * (60 * 20 + 1)  # three vehicles, 60 s at 20 Hz, plus t = 0
    assert float(rows[-1]["t_s"]) == pytest.approx(60.0)


def test_report_recomputes_the_same_metrics(paper_run: Path, tmp_path: Path, capsys):
    out = tmp_path / "m.json"
    assert main(["report", str(paper_run), "--out", str(out)]) == 0
    assert json.loads(out.read_text()) == json.loads((paper_run / "metrics.json").read_text())
    assert "p95_platooning_error_m" in capsys.readouterr().out


def test_report_merges_per_vehicle_logs(paper_run: Path, tmp_path: Path):
    """A vehicle run writes one log per vehicle; report merges them on t_s."""
    with (paper_run / "log.csv").open() as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    vdir = tmp_path / "vehicle-run"
    vdir.mkdir()
    for vid in ("0", "1", "2"):
        with (vdir / f"vehicle{vid}.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(r for r in rows if r[1] == vid)
    assert main(["report", str(vdir)]) == 0
    merged = json.loads((vdir / "metrics.json").read_text())
    original = json.loads((paper_run / "metrics.json").read_text())
    for key in METRIC_KEYS:
        assert merged[key] == pytest.approx(original[key]), key


def test_report_on_a_log_without_lengths_uses_the_convoy_file(
    paper_run: Path, tmp_path: Path, capsys
):
    with (paper_run / "log.csv").open() as f:
        rows = list(csv.DictReader(f))
    log = tmp_path / "bare.csv"
    with log.open("w", newline="") as f:
        fields = [c for c in rows[0] if c != "length_m"]
        w = csv.DictWriter(f, fields, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            # Squeeze follower 1 onto the leader: 0.7 m < (0.779 + 0.97) / 2.
            if r["t_s"] == "30.0" and r["vehicle_id"] == "0":
                lead_x = float(r["x_m"])
            if r["t_s"] == "30.0" and r["vehicle_id"] == "1":
                r["x_m"] = repr(lead_x - 0.7)
            w.writerow(r)
    assert main(["report", str(log)]) == 0
    assert "no vehicle lengths" in capsys.readouterr().out
    assert json.loads((tmp_path / "metrics.json").read_text())["collisions"] == 0
    convoy = tmp_path / "convoy.toml"
    convoy.write_text('[convoy]\nvehicles = ["1/10", "1/6", "1/10"]\n')
    assert main(["report", str(log), "--convoy", str(convoy)]) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["collisions"] == 1


def test_sim_with_convoy_file_burst_loss_and_duration(tmp_path: Path):
    convoy = tmp_path / "convoy.toml"
    convoy.write_text(
        '[convoy]\nscenario = "paper"\nvehicles = ["1/10", "1/10", "1/6", "1/10"]\n'
        "origin = [52.0, 4.37, 0.0]\n"
    )
    out = tmp_path / "run"
    rc = main(
        [
            "sim",
            "--convoy",
            str(convoy),
            "--per",
            "0.3",
            "--loss",
            "gilbert-elliott",
            "--burst",
            "0.5",
            "--duration",
            "5",
            "--seed",
            "7",
            "--out",
            str(out),
            "--no-plots",
        ]
    )
    assert rc == 0
    run = RunConfig.from_dict(load_toml(out / "run.toml")["run"])  # run.toml reloads
    assert run.loss == LossSection(model="gilbert-elliott", mean_burst_s=0.5)
    assert (run.per, run.seed, run.duration_s) == (0.3, 7, 5.0)
    assert run.convoy.vehicles == ("1/10", "1/10", "1/6", "1/10")
    assert run.origin == (52.0, 4.37, 0.0)
    with (out / "log.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert {r["vehicle_id"] for r in rows} == {"0", "1", "2", "3"}
    assert float(rows[0]["lat_deg"]) == pytest.approx(52.0, abs=0.01)
    assert not (out / "gaps.png").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert 0.2 < metrics["delivery_ratio"] < 1.0  # bursts of loss were applied


@pytest.mark.parametrize(
    "argv, words",
    [
        (["sim", "--per", "1.5"], "--per"),
        (["sim", "--policy", "nope"], "unknown policy 'nope'"),
        (["sim", "--scenario", "moon"], "unknown scenario 'moon'"),
        (["sim", "--burst", "2"], "--burst"),
        (["sim", "--vehicle-preset", "1/3"], "unknown vehicle preset '1/3'"),
        (["report", "/nonexistent/run"], "no such log"),
        (["experiment", "per-sweep", "--pers", "0,x"], "--pers"),
        (["experiment", "per-sweep", "--policy", "paper+lader"], "unknown policy"),
        (["sim", "--fault", "crash:0@3"], "bad fault 'crash:0@3': unknown fault kind"),
        (["sim", "--fault", "dead:0@3", "--fault", "dead:7@3"], "no vehicle 7"),
    ],
)
def test_bad_arguments_give_one_clear_line(argv, words, tmp_path: Path, capsys):
    if argv[0] != "report":
        argv = [*argv, "--out", str(tmp_path / "out"), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("openconvoy: error:") and words in err[0]
    assert not (tmp_path / "out").exists()


def test_presets_lists_every_policy_and_vehicle_preset(capsys):
    assert main(["presets"]) == 0
    lines = capsys.readouterr().out.splitlines()
    listed = [ln.split()[0] for ln in lines if ln.startswith("  ")]
    assert listed == [*PRESETS, *VEHICLE_PRESETS]
    event_line = next(ln for ln in lines if ln.split()[0] == "cacc-lookahead1-event")
    assert "lookahead:1, event, constant-time-headway" in event_line


def test_presets_into_a_pipe_the_reader_left_ends_quietly():
    """`openconvoy presets | head -1`: writing into a pipe nobody reads; no traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the first write, as after `head` exits
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "openconvoy.cli", "presets"],
            stdout=write_end,
            stderr=subprocess.PIPE,
            timeout=60,
        )
    finally:
        os.close(write_end)
    assert proc.returncode == 141
    assert proc.stderr == b""


def test_compare_two_runs_shows_differences(paper_run: Path, tmp_path: Path, capsys):
    lossy = tmp_path / "lossy"
    assert main(["sim", "--per", "0.6", "--out", str(lossy), "--quiet", "--no-plots"]) == 0
    capsys.readouterr()
    out = tmp_path / "cmp.json"
    assert main(["compare", str(paper_run), str(lossy), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "B - A" in text and "delivery_ratio" in text
    result = json.loads(out.read_text())
    d = result["metrics"]["delivery_ratio"]
    assert d["a"] == 1.0 and d["diff"] == pytest.approx(d["b"] - 1.0) and d["b"] < 0.5
    assert result["metrics"]["p95_platooning_error_m"]["diff"] > 0


def test_sim_fault_stops_the_convoy_and_writes_events(tmp_path: Path, capsys):
    out = tmp_path / "fault"
    assert (
        main(
            [
                "sim",
                "--fault",
                "dead:0@5",
                "--fault",
                "silent:1@6",
                "--duration",
                "12",
                "--out",
                str(out),
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )
    assert "events.json" in capsys.readouterr().out
    events = json.loads((out / "events.json").read_text())
    assert [(e["t_s"], e["vehicle_id"], e["reason"]) for e in events] == [
        (pytest.approx(5.0), 0, "fault dead:0@5"),
        (pytest.approx(6.0), 1, "fault silent:1@6"),
    ]
    rows = list(csv.DictReader(open(out / "log.csv")))
    last = {r["vehicle_id"]: r for r in rows}
    assert all(abs(float(last[v]["speed_mps"])) < 0.05 for v in ("0", "1", "2"))
    assert 'faults = ["dead:0@5", "silent:1@6"]' in (out / "run.toml").read_text()
