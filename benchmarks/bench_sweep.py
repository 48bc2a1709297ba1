"""Wall time of the paper's PER sweep, printed as one JSON line.

Runs what issue 3 quotes, ``openconvoy experiment per-sweep --policy paper --seeds 3``
(7 PERs x 3 seeds = 21 runs of the 60 s paper scenario at 20 Hz), on every core this
process may use (``--jobs`` to change), figures included, in a temporary directory. Also
reports the single-run wall time, measured alone on one core, and the trend numbers the
sweep shows (mean p95 platooning error and mean speed difference at PER 0 and 0.6).

    python benchmarks/bench_sweep.py [--jobs N] [--seeds 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from openconvoy import __version__
from openconvoy.experiments import RunConfig, run_sim
from openconvoy.experiments.sweep import ExperimentConfig, available_cores, run_experiment


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--jobs", type=int, default=None, help="processes (default: cores available)"
    )
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()

    start = time.perf_counter()
    run_sim(RunConfig(policy="paper", per=0.2))
    single_s = time.perf_counter() - start

    config = ExperimentConfig(policies=("paper",), seeds=tuple(range(args.seeds)))
    jobs = args.jobs or available_cores()
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        result = run_experiment(config, Path(tmp) / "sweep", jobs=jobs, progress=False)
        sweep_s = time.perf_counter() - start
    rows = {r["per"]: r for r in result.rows}
    trend = {
        f"{key}_per_{per:.1f}": round(rows[per][key]["mean"], 4)
        for key in ("p95_platooning_error_m", "mean_speed_difference_mps")
        for per in (0.0, 0.6)
    }
    print(
        json.dumps(
            {
                "benchmark": "per_sweep_paper",
                "command": f"openconvoy experiment per-sweep --policy paper --seeds {args.seeds}",
                "runs": len(result.runs),
                "jobs": jobs,
                "wall_s": round(sweep_s, 2),
                "single_run_wall_s": round(single_s, 2),
                **trend,
                "openconvoy": __version__,
                "python": platform.python_version(),
                "machine": platform.machine(),
            }
        )
    )


if __name__ == "__main__":
    main()
