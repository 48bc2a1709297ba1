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
from pool_tasks import report_quarters, square_or_die

from openconvoy.cli import main
from openconvoy.experiments.batched import tasks as batched_sweep
from openconvoy.experiments.batched.run import STEPPING_SHARE, run_batch
from openconvoy.experiments.executor import (
    ExecutorConfig,
    LocalExecutor,
    Task,
    TaskFailure,
    TasksFailed,
    with_flags,
)
from openconvoy.experiments.runs import RunConfig
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


# --- progress that moves (issue 26): a batch moves the bar as it steps and writes ---


class RecordingBar:
    """tqdm's ``n``/``refresh``/``set_postfix_str``/``close``, recording ``n`` at each refresh."""

    def __init__(self) -> None:
        self.n = 0.0
        self.seen: list[float] = []
        self.closed = False

    def refresh(self) -> None:
        assert not self.seen or self.n > self.seen[-1], "the bar only moves forward"
        self.seen.append(round(self.n, 9))

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_task_reports_move_the_bar_by_its_weight(jobs: int) -> None:
    """A task of weight 4 reporting 1/4, 1/2, (1/4 again: ignored), 3/4 moves the bar to
    1, 2, 3 while it runs, then to 4 as it ends; in this process (jobs 1) and from a
    worker process (jobs 2). A weight-1 task beside it moves by its quarters."""
    bar = RecordingBar()
    with LocalExecutor(jobs=jobs) as ex:
        assert ex.map([Task("batch", report_quarters, 7)], weights=[4], bar=bar) == [7]
    assert bar.seen == [1.0, 2.0, 3.0, 4.0] and bar.closed
    bar = RecordingBar()
    with LocalExecutor(jobs=jobs) as ex:
        tasks = [Task("batch", report_quarters, 7), Task("one", report_quarters, 8)]
        assert ex.map(tasks, weights=[4, 1], bar=bar) == [7, 8]
    assert len(bar.seen) == 2 * 4 and bar.n == 5  # exactly the total at the end


def test_a_batch_reports_its_progress_as_it_steps_and_writes() -> None:
    """``run_batch``'s fractions climb evenly to STEPPING_SHARE while stepping, then by
    equal parts as each run's files are written, ending at 1."""
    configs = [RunConfig(policy="paper", per=0.3, seed=s, duration_s=6.0) for s in range(4)]
    fractions: list[float] = []
    run_batch(configs, on_progress=fractions.append)
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    stepping = [f for f in fractions if f <= STEPPING_SHARE + 1e-12]
    assert len(stepping) >= 25  # about every 1 % of the ticks, not one jump
    assert stepping[-1] == pytest.approx(STEPPING_SHARE, abs=0.01)
    writing = fractions[len(stepping) :]
    share = (1.0 - STEPPING_SHARE) / len(configs)
    assert writing == pytest.approx([STEPPING_SHARE + share * (b + 1) for b in range(4)])


def test_a_batched_sweep_moves_its_bar_within_a_batch(tmp_path: Path) -> None:
    """The sweep's own tasks (one batch of 4 runs, in this process): the bar passes
    fractions of a run before the batch ends, and ends at exactly 4 runs."""
    planned = [
        ("paper", RunConfig(policy="paper", per=p, seed=s, duration_s=4.0))
        for p in (0.0, 0.3)
        for s in (1, 2)
    ]
    dirs = [f"run{i}" for i in range(4)]
    plan = batched_sweep.plan(planned, dirs, [False] * 4, slots=1)
    assert plan.spans == [(0, 4)]  # one batch: before, the bar jumped 0 -> 4
    bar = RecordingBar()
    with LocalExecutor(jobs=1) as ex:
        (result,) = ex.map(plan.tasks, weights=[4], bar=bar)
    assert len(result) == 4 and bar.n == 4
    before_end = [v for v in bar.seen[:-1] if v < 4.0]
    assert len(before_end) >= 20
    assert any(0.0 < v < 1.0 for v in before_end)  # a fraction of one run, while stepping
