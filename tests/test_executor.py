"""The executor seam (issue 15) on this machine: failures named with the other runs kept,
a dying pool worker, the ``[executor]`` table and flags, Ray imported nowhere else.

The Ray executor itself runs against a real local cluster in ``test_ray_executor.py``.
"""

from __future__ import annotations

import ast
import json
import os
import sys
import time
from pathlib import Path

import pytest
from pool_tasks import square_or_die

from openconvoy.cli import main
from openconvoy.experiments.executor import (
    ExecutorConfig,
    LocalExecutor,
    Task,
    TaskFailure,
    TasksFailed,
    with_flags,
)
from openconvoy.experiments.sweep import ExperimentConfig, read_summary, run_experiment

PACKAGE = Path(__file__).resolve().parents[1] / "openconvoy"


def test_a_dying_pool_worker_loses_only_its_own_run():
    tasks = [Task(f"task {i}", square_or_die, i) for i in range(8)]
    with LocalExecutor(jobs=2) as ex:
        results = ex.map(tasks, progress=False)
    # The pool broke with two tasks in flight; each ran again alone, and only task 3's
    # worker died again: the other one and all the rest came back.
    assert [r for i, r in enumerate(results) if i != 3] == [i * i for i in range(8) if i != 3]
    lost = results[3]
    assert isinstance(lost, TaskFailure) and lost.label == "task 3"
    assert lost.error.startswith("BrokenProcessPool") and "alone, on a second try" in lost.where


def test_a_task_submitted_after_the_pool_broke_runs_on_a_fresh_pool():
    """The race the test above can hit: a worker dies after the last result was taken and
    before the next submit, so the pool is already broken when the task is handed over."""
    with LocalExecutor(jobs=2) as ex:
        ex.submit(Task("task 3", square_or_die, 3))
        broken = ex._pool
        deadline = time.monotonic() + 60
        while not broken._broken and time.monotonic() < deadline:  # the pool noticed
            time.sleep(0.01)
        assert broken._broken
        ex.submit(Task("task 4", square_or_die, 4))
        got = {task.label: value for task, value in (ex.wait_one(), ex.wait_one())}
    assert got["task 4"] == 16
    assert isinstance(got["task 3"], TaskFailure) and "alone" in got["task 3"].where


def _sweep(tmp_path: Path) -> ExperimentConfig:
    # A corrupt learned-policy file: its runs fail on the worker when the policy loads.
    broken = tmp_path / "broken.zip"
    broken.write_bytes(b"not a zip file")
    return ExperimentConfig(
        name="fail", policies=("paper", str(broken)), pers=(0.0, 0.5), seeds=(0,), duration_s=3.0
    )


def test_a_failed_run_is_named_and_the_others_are_written(tmp_path: Path):
    out = tmp_path / "sweep"
    with pytest.raises(TasksFailed) as info:
        run_experiment(_sweep(tmp_path), out, jobs=1, progress=False)
    lines = str(info.value).splitlines()
    assert (
        lines[0] == f"2 of 4 runs failed; the other 2 are in {out} (summary.csv covers only them)"
    )
    assert lines[1].startswith("  runs/broken/per_0.00/seed_0: ")
    assert lines[2].startswith("  runs/broken/per_0.50/seed_0: ")
    assert f"(on the driver, pid {os.getpid()} on " in lines[1]
    # The error line says what went wrong with the file.
    assert "zip" in lines[1].lower()
    for per in ("0.00", "0.50"):
        assert (out / "runs" / "paper" / f"per_{per}" / "seed_0" / "log.csv").stat().st_size > 1000
        assert not (out / "runs" / "broken" / f"per_{per}").exists()
    rows = read_summary(out)
    assert [(r["policy"].split("/")[-1], r["runs"]) for r in rows] == [
        ("paper", 1),
        ("paper", 1),
        ("broken.zip", 0),
        ("broken.zip", 0),
    ]
    failures = json.loads((out / "failures.json").read_text())["failures"]
    assert [f["label"] for f in failures] == [
        "runs/broken/per_0.00/seed_0",
        "runs/broken/per_0.50/seed_0",
    ]


def test_the_cli_reports_failed_runs_in_one_line_each_and_exits_1(tmp_path: Path, capsys):
    cfg = _sweep(tmp_path)
    argv = [
        "experiment",
        "per-sweep",
        "--out",
        str(tmp_path / "cli"),
        "--quiet",
        "--no-plots",
        "--jobs",
        "1",
        "--pers",
        "0.2",
        "--seeds",
        "1",
        "--duration",
        "3",
        "--policy",
        "paper",
        "--policy",
        cfg.policies[1],
    ]
    assert main(argv) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("openconvoy: error: 1 of 2 runs failed;")
    assert err[1].startswith("  runs/broken/per_0.20/seed_0: ") and len(err) == 2


def test_executor_table_and_flags(tmp_path: Path):
    exp = tmp_path / "exp.toml"
    exp.write_text(
        '[experiment]\nseeds = 1\n[executor]\nkind = "ray"\naddress = "10.1.2.3:6379"\njobs = 8\n'
    )
    cfg = ExperimentConfig.from_toml(exp)
    assert cfg.executor == ExecutorConfig(kind="ray", address="10.1.2.3:6379", jobs=8)
    # Where runs execute is not part of the experiment: not compared, not in the copy.
    assert cfg == ExperimentConfig(seeds=(0,))
    assert "executor" not in cfg.to_toml()
    # Flags override the table; another kind drops the table's address.
    assert with_flags(cfg.executor, None, "auto", None) == ExecutorConfig("ray", "auto", 8)
    assert with_flags(cfg.executor, "local", None, 2) == ExecutorConfig("local", None, 2)
    exp.write_text('[experiment]\n[executor]\nkind = "dask"\n')
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        ExperimentConfig.from_toml(exp)
    exp.write_text("[experiment]\n[executor]\nnodes = 3\n")
    with pytest.raises(ValueError, match="unknown key.*nodes"):
        ExperimentConfig.from_toml(exp)


def test_bad_executor_flags_are_one_error_line(tmp_path: Path, capsys):
    assert (
        main(["experiment", "per-sweep", "--address", "10.0.0.1:6379", "--out", str(tmp_path)]) == 2
    )
    assert (
        capsys.readouterr().err
        == "openconvoy: error: an executor address needs the ray executor (--executor ray)\n"
    )


def test_missing_ray_is_one_line_naming_the_extra(tmp_path: Path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets without the extra
    assert (
        main(
            [
                "experiment",
                "per-sweep",
                "--executor",
                "ray",
                "--seeds",
                "1",
                "--pers",
                "0",
                "--out",
                str(tmp_path / "x"),
                "--quiet",
            ]
        )
        == 2
    )
    assert capsys.readouterr().err == (
        "openconvoy: error: the ray executor needs Ray, which is not installed: pip install 'openconvoy[cluster]'\n"
    )


def test_only_the_ray_executor_imports_ray():
    importers = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else ([node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            )
            if any(n == "ray" or n.startswith("ray.") for n in names):
                importers.append(path.relative_to(PACKAGE).as_posix())
    assert sorted(set(importers)) == ["experiments/ray_executor.py"]


def test_an_unreachable_cluster_is_one_error_line(tmp_path: Path, capsys):
    pytest.importorskip("ray")
    assert (
        main(
            [
                "experiment",
                "per-sweep",
                "--executor",
                "ray",
                "--address",
                "127.0.0.1:1",
                "--seeds",
                "1",
                "--pers",
                "0",
                "--out",
                str(tmp_path / "x"),
                "--quiet",
            ]
        )
        == 2
    )
    assert capsys.readouterr().err.startswith(
        "openconvoy: error: cannot reach the Ray cluster at 127.0.0.1:1: ConnectionRefusedError"
    )
    assert not (tmp_path / "x").exists()  # nothing written before the cluster answers
