"""Sweeps that survive interruption: Ctrl-C / SIGTERM keep every finished run, ``--resume``
completes the rest with the uninterrupted sweep's ``summary.csv``; runs of different
policies never share a directory; a Ray cluster that does not start is one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.experiments.executor import ExecutorConfig
from openconvoy.experiments.sweep import (
    RESUME_DIR,
    ExperimentConfig,
    policy_dirnames,
    run_experiment,
)

EXPERIMENT = (
    '[experiment]\nname = "resume"\nscenario = "paper"\npolicies = ["paper", "paper+ladder"]\n'
    "pers = [0.0, 0.4]\nseeds = 3\nduration_s = 30.0\n"
)


def _sweep_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "openconvoy.cli", "experiment", "per-sweep", *args]


def _interrupt_after(cmd: list[str], out: Path, records: int, sig: int) -> tuple[int, str]:
    """Start ``cmd``, send ``sig`` once ``records`` runs have finished; its status and stderr.
    The child gets Ctrl-C's default action back: a shell without job control starts its
    background commands with SIGINT ignored, and CPython then installs no handler for it
    (seen when the suite itself ran in the background: the sweep finished, exit 0)."""
    proc = subprocess.Popen(
        cmd,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if len(list((out / RESUME_DIR).glob("run-*.pkl"))) >= records:
            proc.send_signal(sig)
            break
        time.sleep(0.005)
    _, err = proc.communicate(timeout=240)
    return proc.returncode, err


@pytest.mark.e2e
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_an_interrupted_sweep_keeps_its_runs_and_resumes_to_the_same_summary(
    tmp_path: Path, sig: int
):
    exp = tmp_path / "exp.toml"
    exp.write_text(EXPERIMENT)
    whole = tmp_path / "whole"
    run_experiment(ExperimentConfig.from_toml(exp), whole, jobs=1, progress=False, figures=False)
    assert not (whole / RESUME_DIR).exists()  # a complete sweep leaves no resume records

    cut = tmp_path / "cut"
    cmd = _sweep_cmd("--config", str(exp), "--out", str(cut), "--jobs", "1", "--no-batched")
    code, err = _interrupt_after([*cmd, "--no-plots", "--quiet"], cut, 3, sig)
    assert code == 130, err
    kept = sorted(p.parent for p in cut.glob("runs/*/per_*/seed_*/metrics.json"))
    assert 3 <= len(kept) < 12, err  # interrupted between the third and the last run
    line = err.strip().splitlines()[-1]
    assert line == (
        f"openconvoy: interrupted: {len(kept)} of 12 runs finished and are kept in {cut}; "
        f"openconvoy experiment per-sweep --resume {cut} runs the other {12 - len(kept)}"
    )
    assert not (cut / "summary.csv").exists() and not (cut / "summary.json").exists()
    before = {p: (p / "metrics.json").stat().st_mtime_ns for p in kept}

    done = subprocess.run(
        _sweep_cmd("--resume", str(cut), "--jobs", "2", "--no-plots", "--quiet"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert (cut / "summary.csv").read_bytes() == (whole / "summary.csv").read_bytes()
    assert (cut / "summary.json").read_bytes() == (whole / "summary.json").read_bytes()
    for run in whole.glob("runs/*/per_*/seed_*"):
        twin = cut / run.relative_to(whole)
        assert (twin / "log.csv").read_bytes() == (run / "log.csv").read_bytes(), run
    # The kept runs were not run again; the resume records are gone once it is complete.
    assert {p: (p / "metrics.json").stat().st_mtime_ns for p in kept} == before
    assert not (cut / RESUME_DIR).exists()


def test_resume_refuses_what_would_change_the_sweep_or_is_not_a_sweep(tmp_path: Path, capsys):
    exp = tmp_path / "exp.toml"
    exp.write_text(EXPERIMENT.replace("seeds = 3", "seeds = 1").replace("30.0", "2.0"))
    out = tmp_path / "s"
    run_experiment(ExperimentConfig.from_toml(exp), out, jobs=1, progress=False, figures=False)
    assert main(["experiment", "per-sweep", "--resume", str(out), "--pers", "0.1"]) == 2
    assert "--pers cannot change it" in capsys.readouterr().err
    assert main(["experiment", "per-sweep", "--resume", str(out)]) == 2
    assert "holds no interrupted sweep (it is complete" in capsys.readouterr().err
    assert main(["experiment", "per-sweep", "--resume", str(tmp_path / "none")]) == 2
    assert "holds no sweep (no experiment.toml)" in capsys.readouterr().err
    assert main(["experiment", "per-sweep", "--policy", "paper"]) == 2
    assert "needs --out DIR (or --resume DIR)" in capsys.readouterr().err


def test_runs_of_different_policies_never_share_a_directory():
    labels = ["runs/a/policy.zip", "runs/b/policy.zip", "paper", "x/fast.toml+ladder"]
    names = policy_dirnames(labels)
    assert len(set(names.values())) == len(labels)
    assert names["paper"] == "paper" and names["x/fast.toml+ladder"] == "fast+ladder"
    assert names["runs/a/policy.zip"].startswith("policy-")
    assert names == policy_dirnames(labels)  # the same names on every run


def test_a_ray_cluster_that_does_not_start_is_one_line(tmp_path: Path, capsys, monkeypatch):
    import ray  # the cluster extra (make test installs it)

    def slow_start(*args, **kwargs):
        # What Ray 2.x raises on a busy machine (defects-aea1a73.md, D70).
        raise Exception("The current node timed out during startup. This could happen because")

    monkeypatch.setattr(ray, "init", slow_start)
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    code = main(
        ["experiment", "per-sweep", "--policy", "paper", "--pers", "0,0.3", "--seeds", "2"]
        + ["--executor", "ray", "--out", str(tmp_path / "x")]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0] == (
        "openconvoy: error: the Ray cluster (a private cluster of this machine) did not "
        "start: Exception: The current node timed out during startup. This could happen because"
    )
    assert not (tmp_path / "x").exists()


def test_resume_records_are_only_in_an_unfinished_sweep(tmp_path: Path):
    exp = tmp_path / "exp.toml"
    exp.write_text(EXPERIMENT.replace("seeds = 3", "seeds = 1").replace("30.0", "2.0"))
    out = tmp_path / "s"
    os.makedirs(out / RESUME_DIR)
    (out / RESUME_DIR / "run-000000.pkl").write_bytes(b"stale")  # from an earlier sweep here
    run_experiment(ExperimentConfig.from_toml(exp), out, jobs=1, progress=False, figures=False)
    assert not (out / RESUME_DIR).exists()
    assert (out / "summary.csv").is_file()


def test_a_sweep_says_before_the_kernels_first_compile(tmp_path: Path, monkeypatch):
    """The batched kernels' first compile (~30-60 s) is announced, once cached it is not."""
    from openconvoy.envs.vector import jit

    said: list[str] = []
    config = ExperimentConfig(pers=(0.0, 0.3), seeds=1, duration_s=2.0)
    empty = tmp_path / "cache"
    empty.mkdir()
    monkeypatch.setattr(jit, "CACHE_DIR", empty)  # an install whose kernels never compiled
    run_experiment(
        config, tmp_path / "a", jobs=1, progress=False, figures=False, compile_note=said.append
    )
    assert said == [
        "compiling the batched simulator's kernels first (once per install or upgrade, "
        f"~30-60 s; cached in {empty})"
    ]
    (empty / "step.fused_step-1.py311.nbi").write_bytes(b"")  # numba's index, once compiled
    said.clear()
    run_experiment(
        config, tmp_path / "b", jobs=1, progress=False, figures=False, compile_note=said.append
    )
    assert said == []
    # Runs that are not batched say nothing about kernels.
    run_experiment(
        ExperimentConfig(pers=(0.0,), seeds=1, duration_s=2.0, executor=ExecutorConfig(batched=False)),
        tmp_path / "c", jobs=1, progress=False, figures=False, compile_note=said.append,
    )  # fmt: skip
    assert said == []
