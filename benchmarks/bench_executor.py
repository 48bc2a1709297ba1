"""Wall time of one small sweep on the local executor and on the Ray executor, one JSON line.

The same sweep (``--policy paper``, PERs 0, 0.3, 0.6, ``--seeds`` seeds of the 60 s paper
scenario, figures off) runs on the local process pool, then on a private Ray cluster of
this machine's cores (its start-up timed apart; the first sweep on it also starts the Ray
workers). Then ``--rounds`` more sweeps alternate local and Ray (warm workers), and the
fastest of each is reported, so load from other processes hits both alike. The point is
Ray's overhead on one machine, not a speed-up: more machines is what Ray is for. Also
checks that both executors wrote the same ``summary.csv``, byte for byte, and times
``--empty-tasks`` tasks that do nothing on each executor (its own cost per task, which the
load on the machine disturbs less than whole runs).

    python benchmarks/bench_executor.py [--seeds 4] [--rounds 2] [--jobs N]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from openconvoy import __version__
from openconvoy.experiments.executor import ExecutorConfig, LocalExecutor, available_cores
from openconvoy.experiments.sweep import ExperimentConfig, run_experiment


def _noop(x: int) -> int:
    return x


def _per_task_ms(executor, n: int) -> float:
    """Mean wall time per task of ``n`` empty tasks (the executor's own cost), ms."""
    from openconvoy.experiments.executor import Task

    tasks = [Task(str(i), _noop, i) for i in range(n)]
    with executor:
        executor.map(tasks[: executor.slots], progress=False)  # workers started
        start = time.perf_counter()
        executor.map(tasks, progress=False)
        return 1000 * (time.perf_counter() - start) / n


def _sweep(config: ExperimentConfig, out: Path, executor) -> float:
    start = time.perf_counter()
    run_experiment(config, out, executor=executor, progress=False, figures=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--empty-tasks", type=int, default=400)
    parser.add_argument(
        "--jobs", type=int, default=None, help="local processes (default: cores available)"
    )
    args = parser.parse_args()

    import ray

    from openconvoy.experiments.ray_executor import RayExecutor

    config = ExperimentConfig(
        name="bench", policies=("paper",), pers=(0.0, 0.3, 0.6), seeds=tuple(range(args.seeds))
    )
    jobs = args.jobs or available_cores()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        ray.init(
            num_cpus=jobs, include_dashboard=False, log_to_driver=False, logging_level="warning"
        )
        ray_start_s = time.perf_counter() - start
        local, warm = [], []
        try:
            cold_s = _sweep(config, root / "ray-cold", RayExecutor())
            ray_task_ms = _per_task_ms(RayExecutor(), args.empty_tasks)
            local_task_ms = _per_task_ms(LocalExecutor(jobs), args.empty_tasks)
            for i in range(args.rounds):
                local.append(_sweep(config, root / f"local-{i}", ExecutorConfig(jobs=jobs)))
                warm.append(_sweep(config, root / f"ray-{i}", RayExecutor()))
        finally:
            ray.shutdown()
        reference = (root / "ray-cold" / "summary.csv").read_bytes()
        identical = all((d / "summary.csv").read_bytes() == reference for d in root.iterdir())
    local_s, warm_s = min(local), min(warm)
    runs = len(config.pers) * len(config.seeds)
    print(
        json.dumps(
            {
                "benchmark": "executor_local_vs_ray",
                "runs": runs,
                "cpus": jobs,
                "local_wall_s": round(local_s, 2),
                "local_rounds_s": [round(v, 2) for v in local],
                "ray_cluster_start_s": round(ray_start_s, 2),
                "ray_first_sweep_wall_s": round(cold_s, 2),
                "ray_warm_sweep_wall_s": round(warm_s, 2),
                "ray_rounds_s": [round(v, 2) for v in warm],
                "ray_overhead_per_run_ms": round(1000 * (warm_s - local_s) / runs, 1),
                "empty_task_ms_local": round(local_task_ms, 3),
                "empty_task_ms_ray": round(ray_task_ms, 3),
                "summary_csv_identical": identical,
                "ray": ray.__version__,
                "openconvoy": __version__,
                "python": platform.python_version(),
                "machine": platform.machine(),
            }
        )
    )


if __name__ == "__main__":
    main()
