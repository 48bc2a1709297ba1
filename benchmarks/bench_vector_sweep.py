"""The paper's PER sweep and a tuning study, batched and per run, timed side by side.

``openconvoy experiment per-sweep --policy paper --seeds N`` (7 PERs × N seeds of the 60 s
paper scenario, figures included) on the per-run path (one ``ConvoyEnv`` task per run,
``--no-batched``) and the batched path (the default: the runs as a few
``VectorConvoyEnv`` tasks, ``experiments.batched.run``), with every run's log written, and
batched without the run logs (``--no-run-logs``); each on ``--jobs`` processes (default:
the cores available). Then an ``openconvoy tune`` study of ``--trials`` trials (its
default grid: PER 0, 0.3, 0.6 × 2 seeds; trials one at a time) on both paths. Prints one
JSON line: wall and CPU seconds (this process and its workers: on a shared machine CPU
time is the steadier figure), per run and per trial, the load average before and after,
and whether the batched ``summary.csv`` and the studies' objectives equal the per-run
path's (``--seeds`` may differ between calls: ``--out`` keeps each sweep, so the per-run
path can be measured on fewer seeds and compared per run).

    python benchmarks/bench_vector_sweep.py [--seeds 100] [--jobs N] [--trials 4]
        [--paths per-run,batched,batched-no-logs,tune] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from openconvoy import __version__
from openconvoy.experiments.executor import ExecutorConfig, available_cores
from openconvoy.experiments.sweep import ExperimentConfig, run_experiment
from openconvoy.train.tune import TuneConfig, tune

PATHS = ("per-run", "batched", "batched-no-logs", "tune")


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the sweep's workers)."""
    me, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _sweep(seeds: int, jobs: int, path: str, out: Path) -> dict[str, Any]:
    config = ExperimentConfig(name=path, policies=("paper",), seeds=seeds)
    executor = ExecutorConfig(jobs=jobs, batched=path != "per-run")
    start, cpu, load = time.perf_counter(), _cpu_s(), os.getloadavg()[0]
    result = run_experiment(
        config, out / path, executor=executor, progress=False, run_logs=path != "batched-no-logs"
    )
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu
    n = len(result.runs)
    return {
        "runs": n,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "cpu_s_per_run": round(cpu / n, 4),
        "load_average": [round(load, 1), round(os.getloadavg()[0], 1)],
    }


def _tune(trials: int, batched: bool) -> dict[str, Any]:
    start, cpu = time.perf_counter(), _cpu_s()
    result = tune(TuneConfig(trials=trials), executor=ExecutorConfig(jobs=1, batched=batched))
    wall, cpu = time.perf_counter() - start, _cpu_s() - cpu
    return {
        "s_per_trial": round(wall / (trials + 1), 2),  # the base policy's evaluation too
        "cpu_s_per_trial": round(cpu / (trials + 1), 2),
        "values": [h["value"] for h in result.history],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--paths", default=",".join(PATHS), help=f"some of {', '.join(PATHS)}")
    ap.add_argument(
        "--out",
        metavar="DIR",
        help="keep the sweeps in DIR/<path> (a later call compares with those already there)",
    )
    args = ap.parse_args()
    paths = [p for p in args.paths.split(",") if p]
    jobs = args.jobs or available_cores()
    out: dict[str, Any] = {"benchmark": "vector_sweep", "seeds": args.seeds, "jobs": jobs}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(args.out or tmp)
        for path in (p for p in paths if p != "tune"):
            shutil.rmtree(where / path, ignore_errors=True)
            out[path] = _sweep(args.seeds, jobs, path, where)
        summaries = {
            p: (where / p / "summary.csv").read_bytes()
            for p in PATHS
            if (where / p / "summary.csv").is_file()
        }
    if "per-run" in summaries:
        out["summary_identical"] = {
            p: s == summaries["per-run"] for p, s in summaries.items() if p != "per-run"
        }
    if "per-run" in out and "batched" in out:
        a, b = out["per-run"], out["batched"]
        out["cpu_per_run_speedup"] = round(a["cpu_s_per_run"] / b["cpu_s_per_run"], 1)
    if "tune" in paths:
        per_run, batched = _tune(args.trials, False), _tune(args.trials, True)
        out["tune"] = {
            "trials": args.trials,
            "per_run": {k: v for k, v in per_run.items() if k != "values"},
            "batched": {k: v for k, v in batched.items() if k != "values"},
            "objectives_identical": per_run["values"] == batched["values"],
        }
    out.update(
        openconvoy=__version__,
        python=platform.python_version(),
        machine=platform.machine(),
        cpus=os.cpu_count(),
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
