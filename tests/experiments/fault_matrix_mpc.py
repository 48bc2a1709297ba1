"""The fault matrix of ``test_fault_matrix.py`` for the nine MPC presets, run outside the
suite (each run is its own ``ConvoyEnv``: 2,916 runs, ~18 min on two cores):

    python tests/experiments/fault_matrix_mpc.py

Prints progress and ``MPC fault matrix: N runs, K collided``; a collision is any two
convoy vehicles closer than their half lengths, any pair, any tick (as the suite's: the
same ``fault_matrix_tasks.run_worst``, on the project's local executor)."""

from __future__ import annotations

import time

from fault_matrix_tasks import runs_worst

from openconvoy.experiments.executor import LocalExecutor, Task, TaskFailure
from openconvoy.experiments.runs import RunConfig

SCEN = {
    "paper": (10.0, 40.0),
    "track": (10.0, 100.0),
    "emergency-braking": (3.0, 15.0),
    "highway-cut-in": (2.0, 8.0),
}
KINDS = ("halt", "silent", "dead")


def matrix(presets: list[str]) -> list[RunConfig]:
    """Every run of the matrix for ``presets``: scenario × preset × fault × PER × seed."""
    return [
        RunConfig(
            scenario=s, policy=p, per=per, seed=seed, duration_s=d, faults=(f"{k}:{v}@{t:g}",)
        )
        for s, (t, d) in SCEN.items()
        for p in presets
        for k in KINDS
        for v in range(3)
        for per in (0.0, 0.3, 0.6)
        for seed in (0, 1, 2)
    ]


def run(configs: list[RunConfig], jobs: int = 2) -> list[tuple[RunConfig, float]]:
    """Each run of ``configs`` (a task each, on ``jobs`` workers) with its smallest bumper
    gap (m); prints each collision as it comes back. A failed run raises."""
    tasks = [
        Task(f"{c.scenario} {c.policy} {c.faults[0]} {c.per} {c.seed}", runs_worst, [c])
        for c in configs
    ]

    def report(i: int, result: object) -> None:
        if isinstance(result, list) and result[0] <= 0.0:
            print("collided", tasks[i].label, round(result[0], 3), flush=True)

    with LocalExecutor(jobs=jobs) as ex:
        results = ex.map(tasks, desc="MPC fault matrix", on_result=report)
    failed = [r.line() for r in results if isinstance(r, TaskFailure)]
    if failed:
        raise RuntimeError("\n".join(failed))
    return [(c, r[0]) for c, r in zip(configs, results)]


if __name__ == "__main__":
    from openconvoy.policies.presets import PRESETS

    mpc = [k for k, v in PRESETS.items() if v.mpc is not None]
    t0 = time.time()
    worst = run(matrix(mpc))
    bad = [w for _, w in worst if w <= 0.0]
    print(
        f"MPC fault matrix: {len(worst)} runs, {len(bad)} collided, {time.time() - t0:.0f} s",
        flush=True,
    )
