"""The paper's PER sweep and a tuning study, batched and per run, timed side by side.

``openconvoy experiment per-sweep --policy paper --seeds N`` (7 PERs × N seeds of the 60 s
paper scenario, figures included) on the per-run path (one ``ConvoyEnv`` task per run,
``--no-batched``) and the batched path (the default: the runs as a few
``VectorConvoyEnv`` tasks, ``experiments.batched``), with every run's log written, and
batched without the run logs (``--no-run-logs``); each on ``--jobs`` processes (default:
the cores available). Then an ``openconvoy tune`` study of ``--trials`` trials (its
default grid: PER 0, 0.3, 0.6 × 2 seeds; trials one at a time) on both paths. Prints one
JSON line: wall times, per-run and per-trial seconds, and whether the batched
``summary.csv`` and the studies' objectives equal the per-run path's.

    python benchmarks/bench_vector_sweep.py [--seeds 100] [--jobs N] [--trials 4]
        [--paths per-run,batched,batched-no-logs,tune] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
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


def _sweep(seeds: int, jobs: int, path: str, out: Path) -> dict[str, Any]:
    config = ExperimentConfig(name=path, policies=("paper",), seeds=seeds)
    executor = ExecutorConfig(jobs=jobs, batched=path != "per-run")
    start = time.perf_counter()
    result = run_experiment(
        config, out / path, executor=executor, progress=False, run_logs=path != "batched-no-logs"
    )
    wall = time.perf_counter() - start
    n = len(result.runs)
    return {"wall_s": round(wall, 1), "runs": n, "s_per_run": round(wall / n, 4)}


def _tune(trials: int, batched: bool) -> dict[str, Any]:
    start = time.perf_counter()
    result = tune(TuneConfig(trials=trials), executor=ExecutorConfig(jobs=1, batched=batched))
    wall = time.perf_counter() - start
    return {
        "wall_s": round(wall, 1),
        "s_per_trial": round(wall / (trials + 1), 2),  # the base policy's evaluation too
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
        out["sweep_speedup"] = round(out["per-run"]["wall_s"] / out["batched"]["wall_s"], 1)
    if "tune" in paths:
        per_run, batched = _tune(args.trials, False), _tune(args.trials, True)
        out["tune"] = {
            "trials": args.trials,
            "per_run_s_per_trial": per_run["s_per_trial"],
            "batched_s_per_trial": batched["s_per_trial"],
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
