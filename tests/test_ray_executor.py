"""The Ray executor against a real local Ray cluster (2 CPUs, one for the whole module):
a sweep byte-identical to the local executor's, a worker killed mid-sweep, a tuning study
resumed after its driver is killed, several training runs shipped back to the driver."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip("ray", reason="the cluster extra (openconvoy[cluster]) is not installed")

from openconvoy.cli import main  # noqa: E402
from openconvoy.experiments.executor import (  # noqa: E402
    Executor,
    ExecutorConfig,
    Task,
    TasksFailed,
)
from openconvoy.experiments.ray_executor import RayExecutor  # noqa: E402
from openconvoy.experiments.sweep import ExperimentConfig, read_summary, run_experiment  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cluster() -> Any:
    """A local Ray cluster of 2 CPUs; its GCS address (other drivers connect to it)."""
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        _node_ip_address="127.0.0.1",
        object_store_memory=100 * 1024 * 1024,
        log_to_driver=False,
        logging_level="warning",
    )
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


def _experiment(tmp_path: Path) -> ExperimentConfig:
    # A policy file on the driver only: the workers get its bytes.
    policy = tmp_path / "gentle.toml"
    policy.write_text('[policy]\nbase = "paper"\nspeed = { kind = "pd", kp = 0.5, kd = 1.1 }\n')
    return ExperimentConfig(
        name="ray",
        policies=("paper+ladder", str(policy)),
        pers=(0.0, 0.5),
        seeds=(0, 1),
        duration_s=4.0,
    )


def test_a_ray_sweep_is_byte_identical_to_the_local_one(cluster: str, tmp_path: Path):
    cfg = _experiment(tmp_path)
    local = run_experiment(cfg, tmp_path / "local", jobs=1, progress=False, figures=False)
    executor = RayExecutor()
    assert executor.address == cluster and executor.slots == 2
    run_experiment(cfg, tmp_path / "ray", executor=executor, progress=False, figures=False)
    assert (tmp_path / "ray" / "summary.csv").read_bytes() == (
        tmp_path / "local" / "summary.csv"
    ).read_bytes()
    logs = sorted(p.relative_to(tmp_path / "local") for p in (tmp_path / "local").rglob("log.csv"))
    assert len(logs) == 8
    for rel in logs:
        assert (tmp_path / "ray" / rel).read_bytes() == (tmp_path / "local" / rel).read_bytes(), rel
    rows = read_summary(tmp_path / "ray")
    assert [r["runs"] for r in rows] == [2, 2, 2, 2]
    assert local.rows[1]["delivery_ratio"]["mean"] < 0.6  # PER 0.5 really applied


class _ExitOn:
    """A task's function that makes its worker process exit at once (as a segfault or the
    OOM killer would) when ``die`` is set."""

    def __init__(self, fn: Any, die: bool) -> None:
        self.fn, self.die = fn, die

    def __call__(self, arg: Any) -> Any:
        if self.die:
            os._exit(9)
        return self.fn(arg)


class _KillOne(Executor):
    """The Ray executor with one run's worker killed mid-run (a fault at the edge)."""

    kind = "ray"

    def __init__(self, victim: str) -> None:
        self.inner, self.victim, self.original = RayExecutor(), victim, {}

    @property
    def slots(self) -> int:
        return self.inner.slots

    def submit(self, task: Task) -> None:
        wrapped = Task(task.label, _ExitOn(task.fn, task.label == self.victim), task.arg)
        self.original[id(wrapped)] = task
        self.inner.submit(wrapped)

    def wait_one(self) -> tuple[Task, Any]:
        task, value = self.inner.wait_one()
        return self.original.pop(id(task)), value

    def close(self) -> None:
        self.inner.close()


def test_a_worker_killed_mid_sweep_loses_only_its_run(cluster: str, tmp_path: Path):
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # _ExitOn is test code
    # One task per run (not batched), so that one run's worker is the one killed.
    cfg = dataclasses.replace(_experiment(tmp_path), executor=ExecutorConfig(batched=False))
    victim = "runs/gentle/per_0.50/seed_0"
    out = tmp_path / "killed"
    with pytest.raises(TasksFailed) as info:
        run_experiment(cfg, out, executor=_KillOne(victim), progress=False)
    lines = str(info.value).splitlines()
    assert (
        lines[0] == f"1 of 8 runs failed; the other 7 are in {out} (summary.csv covers only them)"
    )
    # The worker is named: its pid, host, IP and Ray node, reported before the run started.
    assert len(lines) == 2 and re.fullmatch(
        rf"  {victim}: WorkerCrashedError: The worker died unexpectedly while executing this task\. [^\[]*"
        r"\(on Ray worker pid \d+ on \S+ [\d.:a-f]+, node [0-9a-f]{8}\)",
        lines[1],
    ), lines[1]
    assert not (out / victim).exists()
    assert len(list(out.rglob("log.csv"))) == 7
    assert [r["runs"] for r in read_summary(out)] == [2, 2, 2, 1]
    assert json.loads((out / "failures.json").read_text())["failures"][0]["label"] == victim


def _tune_argv(address: str, storage: Path, out: Path, trials: int) -> list[str]:
    return [
        "tune",
        "--executor",
        "ray",
        "--address",
        address,
        "--storage",
        str(storage),
        "--study-name",
        "resume",
        "--trials",
        str(trials),
        "--per",
        "0.3",
        "--seeds",
        "1000",
        "--duration",
        "8",
        "--out",
        str(out),
        "--no-progress",
    ]


def _trials(storage: Path) -> list[Any]:
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    try:
        study = optuna.load_study(
            study_name="resume", storage=JournalStorage(JournalFileBackend(str(storage)))
        )
    except KeyError:
        return []
    return study.get_trials(deepcopy=True)


@pytest.mark.e2e
def test_a_tuning_study_resumes_after_its_driver_is_killed(cluster: str, tmp_path: Path):
    from optuna.trial import TrialState

    storage, out = tmp_path / "study.journal", tmp_path / "tuned.toml"
    driver = subprocess.Popen(
        [sys.executable, "-m", "openconvoy.cli", *_tune_argv(cluster, storage, out, 200)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 180
        while sum(t.state == TrialState.COMPLETE for t in _trials(storage) if storage.exists()) < 3:
            assert driver.poll() is None, driver.stderr.read().decode()
            assert time.monotonic() < deadline, "the cluster ran no trials"
            time.sleep(0.2)
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    before = _trials(storage)
    finished = [t for t in before if t.state == TrialState.COMPLETE]
    # A trial killed before its parameters were all drawn was never evaluated: it is not
    # a candidate to evaluate again.
    orphans = [
        t
        for t in before
        if t.state == TrialState.RUNNING and set(t.params) >= set(finished[0].params)
    ]
    assert len(finished) >= 3 and not out.exists()

    target = len(finished) + 3
    assert main(_tune_argv(cluster, storage, out, target)) == 0
    after = _trials(storage)
    complete = [t for t in after if t.state == TrialState.COMPLETE]
    assert len(complete) == target
    # The finished trials are kept as they were, none evaluated again ...
    kept = {t.number: (t.params, t.value) for t in complete}
    assert all(kept[t.number] == (t.params, t.value) for t in finished)
    assert len({tuple(sorted(t.params.items())) for t in complete}) == target
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["evaluated_this_run"] == 3 and summary["requeued"] == len(orphans)
    assert len(summary["trials"]) == target
    # ... and the runs the killed driver left unfinished are evaluated once, in the resumed run.
    new = [t for t in complete if t.number not in {f.number for f in finished}]
    for orphan in orphans:
        assert [t.user_attrs.get("requeued_from") for t in new if t.params == orphan.params] == [
            orphan.number
        ]
    assert summary["best_value"] <= summary["base_value"]


FAST_TRAIN = (
    "total_steps = 512\nn_envs = 1\ncheckpoint_every = 0\nvalidation_pers = [0.3]\n"
    "validation_seeds = [1000]\nvalidation_duration_s = 3.0\n[ppo]\nn_steps = 256\n"
)


@pytest.mark.e2e
def test_training_runs_on_the_cluster_come_back_as_run_directories(
    cluster: str, tmp_path: Path, capsys
):
    from openconvoy.policies import load_policy
    from openconvoy.policies.learned import read_zip_meta
    from openconvoy.train.config import load_train_config

    base = tmp_path / "soft.toml"  # a residual base on the driver only
    base.write_text('[policy]\nbase = "paper"\nspeed = { kind = "pd", kp = 0.4, kd = 1.1 }\n')
    cfg = tmp_path / "fast.toml"
    cfg.write_text(f'{FAST_TRAIN}[env]\nbase_policy = "{base}"\n')
    out = tmp_path / "multi"
    assert (
        main(
            [
                "train",
                "--config",
                str(cfg),
                "--seeds",
                "0",
                "1",
                "--executor",
                "ray",
                "--address",
                cluster,
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    runs = json.loads((out / "runs.json").read_text())["runs"]
    assert [(r["name"], r["seed"], r["steps"]) for r in runs] == [
        ("seed_0", 0, 512),
        ("seed_1", 1, 512),
    ]
    for name in ("seed_0", "seed_1"):
        for f in (
            "config.toml",
            "policy.zip",
            "last.zip",
            "policy.json",
            "train.json",
            "validation.json",
        ):
            assert (out / name / f).is_file(), (name, f)
        assert list((out / name / "tb").rglob("events.out.tfevents.*"))
        # Paths the run recorded name the driver's directory, not the worker's.
        validation = json.loads((out / name / "validation.json").read_text())
        assert Path(validation["chosen"]).read_bytes() == (out / name / "policy.zip").read_bytes()
        assert load_policy(str(out / name / "policy.zip")) is not None
    # The run's config names the driver's base file: `train --config RUN/config.toml` reruns it.
    given, runs_cfg = (
        load_train_config(cfg),
        [load_train_config(out / n / "config.toml") for n in ("seed_0", "seed_1")],
    )
    assert runs_cfg == [given, dataclasses.replace(given, seed=1)] and given.env.base_policy == str(
        base
    )
    assert read_zip_meta(out / "seed_0" / "policy.zip").base.speed.kp == 0.4
    assert (out / "seed_0" / "last.zip").read_bytes() != (out / "seed_1" / "last.zip").read_bytes()
    assert "seed_1/policy.zip  (512 steps" in capsys.readouterr().out
