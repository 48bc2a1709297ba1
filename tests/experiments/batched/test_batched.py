"""The batched path of sweeps and tuning against the per-run path (one ``ConvoyEnv`` per
run): the same run directory byte for byte, the same trial objective to the bit, and the
configurations the batched env refuses run per run, saying so in one line."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.cli import main
from openconvoy.experiments.batched import tasks as batched_sweep
from openconvoy.experiments.batched.run import refusal
from openconvoy.experiments.executor import ExecutorConfig, TaskFailure
from openconvoy.experiments.runs import ConvoySection, LossSection, RunConfig
from openconvoy.experiments.sweep import ExperimentConfig, read_summary, run_experiment
from openconvoy.policies.spec import classical_config
from openconvoy.testing import tree_files
from openconvoy.train.tune import TuneConfig, grid_batched, grid_evaluator, with_values

# 25 s: past the leader's first speed change.
SWEEP = ExperimentConfig(
    name="b", policies=("paper",), pers=(0.0, 0.3, 0.6), seeds=3, duration_s=25.0
)


def _files(root: Path) -> dict[str, bytes]:
    return tree_files(root, skip=("manifest.json",))  # the manifest names its own directory


def _same_files_on_both_paths(config: ExperimentConfig, tmp_path: Path) -> dict[str, bytes]:
    """Run ``config`` per run and batched (which must not fall back, saying why); assert
    the two trees' files are byte-identical and return them."""
    said: list[str] = []
    one = ExecutorConfig(jobs=1, batched=False)
    run_experiment(config, tmp_path / "per_run", progress=False, figures=False, executor=one)
    run_experiment(config, tmp_path / "batched", progress=False, figures=False, say=said.append)
    a, b = _files(tmp_path / "per_run"), _files(tmp_path / "batched")
    assert said == [] and sorted(a) == sorted(b)
    for name in a:
        assert a[name] == b[name], name
    return a


def test_a_batched_sweep_writes_the_per_run_sweeps_directory_byte_for_byte(tmp_path: Path):
    said: list[str] = []
    per_run = run_experiment(
        SWEEP,
        tmp_path / "per_run",
        progress=False,
        figures=False,
        executor=ExecutorConfig(jobs=1, batched=False),
    )
    batched = run_experiment(
        SWEEP, tmp_path / "batched", progress=False, figures=False, jobs=1, say=said.append
    )
    assert said == [] and batched.per_run == {}
    a, b = _files(tmp_path / "per_run"), _files(tmp_path / "batched")
    assert len([name for name in a if name.endswith("log.csv")]) == 9
    assert sorted(a) == sorted(b)
    for name in a:
        assert a[name] == b[name], name
    assert per_run.rows == batched.rows
    # Not vacuous: PER 0.6 lost messages and moved the numbers.
    rows = read_summary(tmp_path / "batched")
    assert rows[2]["delivery_ratio"]["mean"] < 0.5 < rows[0]["delivery_ratio"]["mean"]
    assert rows[2]["p95_platooning_error_m"]["mean"] > rows[0]["p95_platooning_error_m"]["mean"]
    # The 9 runs were 1 batched task (9 with the per-run path).
    planned = SWEEP.run_configs()
    dirs = [str(i) for i in range(len(planned))]
    tasks = batched_sweep.plan(planned, dirs, [False] * len(planned), slots=1)
    assert tasks.spans == [(0, 9)]
    # Without the run logs: the same summary, each run's metrics.json and no log.csv.
    run_experiment(SWEEP, tmp_path / "no_logs", progress=False, figures=False, run_logs=False)
    c = _files(tmp_path / "no_logs")
    assert c["summary.csv"] == a["summary.csv"] and not any(n.endswith("log.csv") for n in c)
    assert {n for n in c if n.endswith("metrics.json")} == {
        n for n in a if n.endswith("metrics.json")
    }


def test_gps_noise_and_latency_jitter_sweep_batched_byte_for_byte(tmp_path: Path):
    noisy = ExperimentConfig(name="n", policies=("paper",), pers=(0.0, 0.4), seeds=2,
                             duration_s=10.0)  # fmt: skip
    noisy = dataclasses.replace(
        noisy,
        convoy=dataclasses.replace(noisy.convoy, gps_noise_m=0.2),
        loss=dataclasses.replace(noisy.loss, latency_s=0.05, jitter_s=0.1),
    )
    _same_files_on_both_paths(noisy, tmp_path)


def test_a_tune_trials_objective_is_the_same_on_both_paths(tmp_path: Path):
    config = TuneConfig(pers=(0.0, 0.5), seeds=(1000, 1001), duration_s=25.0)
    assert grid_batched(config) == (True, None)
    base = classical_config("paper")
    candidate = with_values(base, {"speed.kp": 0.6, "heading.gain": 0.3}, "trial")
    one = grid_evaluator(config, tmp_path, batched=False)(candidate)
    assert grid_evaluator(config, tmp_path, batched=True)(candidate) == one
    assert grid_evaluator(config, tmp_path, batched=True)(base) != one  # its own number


def test_what_the_batched_env_refuses_runs_per_run_in_one_line(tmp_path: Path):
    run = RunConfig(policy="paper", per=0.2, duration_s=2.0)
    assert refusal(run) is None
    assert refusal(dataclasses.replace(run, convoy=ConvoySection(gps_noise_m=0.2))) is None
    assert refusal(dataclasses.replace(run, loss=LossSection(latency_s=0.1, jitter_s=0.05))) is None
    assert refusal(dataclasses.replace(run, convoy=ConvoySection(ranging=True))) is None
    assert refusal(dataclasses.replace(run, faults=("forge:1@1",), auth="off")) is None
    assert "highway" in refusal(dataclasses.replace(run, scenario="highway-cut-in"))
    learned = dataclasses.replace(run, policy=str(tmp_path / "p.zip"))
    assert "bit-equal" in refusal(learned)  # not loaded: the per-run runs report it
    mixed = ExperimentConfig(policies=("paper", "paper+ladder"), pers=(0.2,), seeds=1)
    mixed = dataclasses.replace(mixed, duration_s=2.0, scenario="highway-cut-in")
    said: list[str] = []
    plan = batched_sweep.plan(mixed.run_configs(), ["a", "b"], [False, False], slots=1)
    batched_sweep.say_per_run(plan, said.append)
    assert said == [
        f"{label}: one ConvoyEnv per run (the batched env has no traffic (highway scenarios))"
        for label in ("paper", "paper+ladder")
    ]


def test_ranging_sweep_batched_byte_for_byte(tmp_path: Path):
    """Followers with a ranging sensor, the ladder on: the reading and its noise are the
    same on both paths, so are the files."""
    sweep = ExperimentConfig(name="r", policies=("paper+ladder",), pers=(0.0, 0.8), seeds=2,
                             duration_s=20.0)  # fmt: skip
    sweep = dataclasses.replace(sweep, convoy=dataclasses.replace(sweep.convoy, ranging=True))
    a = _same_files_on_both_paths(sweep, tmp_path)
    logs = [a[n] for n in a if n.endswith("log.csv")]
    assert len(logs) == 4 and any(b"degraded" in log for log in logs)


def test_emergency_stops_sweep_batched_writes_run_sims_events_json(tmp_path: Path):
    """Event-triggered CACC of full-size cars: emergency stops at PER 0.9, and since
    issue 22 at PER 0 too: the rule takes a silent leader as braking since its last
    message (a dead one is silent too), and 0.45 s of the event trigger's silence at
    25 m/s and 0.6 s headway leave less than that needs. Each run directory has
    ``events.json`` exactly when the run had events, the same bytes on both paths (the
    per-run path's is ``run_sim``'s)."""
    sweep = ExperimentConfig(name="e", scenario="emergency-braking",
                             policies=("cacc-allpred-event",), pers=(0.0, 0.9), seeds=2)  # fmt: skip
    a = _same_files_on_both_paths(sweep, tmp_path)
    runs = {n.rsplit("/", 1)[0] for n in a if n.endswith("metrics.json")}
    with_events = {n.rsplit("/", 1)[0] for n in a if n.endswith("events.json")}
    assert len(runs) == 4 and with_events == runs
    for run in with_events:
        events = json.loads(a[f"{run}/events.json"])
        assert events and all(e["reason"].startswith("emergency stop: gap") for e in events)
    # Without run logs, the events are still written (and the summary is unchanged).
    run_experiment(sweep, tmp_path / "no_logs", progress=False, figures=False, run_logs=False)
    c = _files(tmp_path / "no_logs")
    assert {n: c[n] for n in c if n.endswith("events.json")} == {
        n: a[n] for n in a if n.endswith("events.json")
    }
    assert c["summary.csv"] == a["summary.csv"]


@pytest.mark.parametrize("auth", ["required", "off"])
def test_forge_runs_batched_are_run_sims_files(tmp_path: Path, auth: str):
    """``run_batch`` of runs with a forger (and a ranging sensor) gives ``run_sim``'s
    ``log.csv`` and ``metrics.json`` byte for byte, with authentication on and off."""
    from openconvoy.experiments.batched.run import run_batch
    from openconvoy.experiments.runs import run_sim

    base = RunConfig(policy="paper", duration_s=15.0, faults=("forge:0@4",), auth=auth)
    configs = [dataclasses.replace(base, per=p, seed=s) for p, s in ((0.0, 1), (0.4, 2))]
    configs.append(dataclasses.replace(configs[1], convoy=ConvoySection(ranging=True)))
    got = [r["files"] for part in (configs[:2], configs[2:]) for r in run_batch(part)]
    for i, config in enumerate(configs):
        run_sim(config, tmp_path / str(i))
        assert sorted(got[i]) == ["events.json", "log.csv", "metrics.json"]
        for name in got[i]:
            assert got[i][name] == (tmp_path / str(i) / name).read_bytes(), (i, name)
    assert json.loads(got[0]["events.json"])[0] == {
        "t_s": 4.0, "vehicle_id": 0, "reason": "fault forge:0@4"
    }  # fmt: skip
    chased = json.loads(got[0]["metrics.json"])["min_gap_m"] < 10.0
    assert chased == (auth == "off")


# A fault sweep: PERs x seeds of the paper scenario, 20 s (the fault well inside it).
FAULTED = ExperimentConfig(name="f", policies=("paper",), pers=(0.0, 0.4), seeds=2,
                           duration_s=20.0)  # fmt: skip


def _summary_without_faults(tmp_path: Path) -> list[dict]:
    run_experiment(FAULTED, tmp_path / "healthy", progress=False, figures=False, jobs=1)
    return read_summary(tmp_path / "healthy")


def _means(rows: list[dict], key: str) -> list[float]:
    return [r[key]["mean"] for r in rows]


@pytest.mark.parametrize("fault", ["halt:1@8", "silent:1@6", "dead:0@6"])
def test_a_fault_sweep_batched_byte_for_byte(tmp_path: Path, fault: str):
    """Vehicle 1 braking to rest (``halt``), its radio dead (``silent``), the leader
    braking and mute (``dead``): the batched sweep writes the per-run sweep's files, and
    the fault moved the numbers (a sweep without it is another summary)."""
    sweep = dataclasses.replace(FAULTED, faults=(fault,))
    a = _same_files_on_both_paths(sweep, tmp_path)
    assert f'faults = ["{fault}"]' in a["experiment.toml"].decode()
    healthy = _summary_without_faults(tmp_path)
    faulted = read_summary(tmp_path / "batched")
    assert _means(faulted, "p95_platooning_error_m") != _means(healthy, "p95_platooning_error_m")
    if fault.startswith("halt"):  # the leader drives on from the stopped vehicle 1
        assert min(_means(faulted, "p95_platooning_error_m")) > 5.0
        assert max(_means(healthy, "p95_platooning_error_m")) < 0.5


def test_a_forged_leader_sweep_batched_byte_for_byte(tmp_path: Path):
    """A forger claiming to be the leader, 1 km ahead of it, from 4 s: with ``security.auth``
    off the followers chase it (min gap 15 m -> under 2 m) on both paths alike; with
    authentication it is rejected and the summary is the healthy sweep's. (Under 2 m
    before issue 22; the braking rule that assumes the vehicle ahead may brake now holds
    the chase to about 4.4-5.1 m.)"""
    sweep = dataclasses.replace(FAULTED, faults=("forge:0@4",), auth="off")
    a = _same_files_on_both_paths(sweep, tmp_path)
    assert 'auth = "off"' in a["experiment.toml"].decode()
    healthy = _summary_without_faults(tmp_path)
    forged = read_summary(tmp_path / "batched")
    assert max(_means(forged, "min_gap_m")) < 6.0 < 14.0 < min(_means(healthy, "min_gap_m"))
    rejected = dataclasses.replace(sweep, auth="required")
    run_experiment(rejected, tmp_path / "rejected", progress=False, figures=False, jobs=1)
    assert (tmp_path / "rejected" / "summary.csv").read_bytes() == (
        tmp_path / "healthy" / "summary.csv"
    ).read_bytes()


def test_a_tune_trials_objective_under_a_fault_is_the_same_on_both_paths(tmp_path: Path):
    """Tuning for a braking predecessor: the trial's grid runs the fault on both paths
    to the same objective, and it is not the healthy grid's."""
    config = TuneConfig(pers=(0.0, 0.5), seeds=(1000, 1001), duration_s=20.0,
                        faults=("halt:1@8",))  # fmt: skip
    assert grid_batched(config) == (True, None)
    candidate = with_values(classical_config("paper"), {"speed.kp": 0.6}, "trial")
    one = grid_evaluator(config, tmp_path, batched=False)(candidate)
    assert grid_evaluator(config, tmp_path, batched=True)(candidate) == one
    healthy = dataclasses.replace(config, faults=())
    assert grid_evaluator(healthy, tmp_path, batched=True)(candidate) < one


def test_a_failed_batch_fails_each_of_its_runs_by_name():
    lost = TaskFailure("runs/a .. runs/c (batch of 2)", "pid 1 on h", "MemoryError")
    assert batched_sweep.expand_one({"ok": 1}, 1, ["runs/a"]) == [{"ok": 1}]
    out = batched_sweep.expand_one(lost, 2, ["runs/b", "runs/c"])
    assert out == [TaskFailure(d, "pid 1 on h", "MemoryError") for d in ("runs/b", "runs/c")]


def test_the_cli_flags(tmp_path: Path, capsys):
    argv = ["experiment", "per-sweep", "--pers", "0.2", "--seeds", "1", "--duration", "2"]
    argv += ["--no-plots", "--jobs", "1", "--no-run-logs", "--out"]
    assert main([*argv, str(tmp_path / "a"), "--no-batched"]) == 0
    assert main([*argv, str(tmp_path / "b"), "--batched"]) == 0
    assert "1 run metrics" in capsys.readouterr().out
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert a == b and not any(n.endswith("log.csv") for n in a)
    # tune: the base policy and its own values as the one trial, on both paths.
    objectives = []
    for flag in ("--no-batched", "--batched"):
        out = tmp_path / f"tuned{flag}.toml"
        tune = ["tune", "--trials", "1", "--per", "0.4", "--seeds", "1000", "--duration", "4"]
        assert main([*tune, "--out", str(out), "--no-progress", flag]) == 0
        summary = json.loads(out.with_suffix(".json").read_text())
        objectives.append((summary["base_value"], summary["best_value"]))
    assert objectives[0] == objectives[1] and objectives[0][0] == objectives[0][1]
