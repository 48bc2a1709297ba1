"""MPC with shared plans against MPC state-only on ``paper`` under loss (issue 24).

Runs ``paper-mpc`` and ``paper-mpc-state`` (and the paper's PD for reference) at PER 0 to
0.8 over ``--seeds`` seeds with ``run_sim`` and prints, per policy and PER, the p95
platooning error (mean and worst seed, m), the collisions and the smallest gap (m)::

    python benchmarks/mpc_loss_table.py --seeds 10
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from openconvoy.experiments.runs import RunConfig, run_sim


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--policies", default="paper-mpc,paper-mpc-state,paper")
    ap.add_argument("--pers", default="0,0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8")
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()}")
    print(
        "| policy | PER | p95 error mean (m) | p95 error worst seed (m) | collisions | min gap (m) |"
    )
    print("|---|---|---|---|---|---|")
    for policy in args.policies.split(","):
        for per in (float(p) for p in args.pers.split(",")):
            p95, coll, gap = [], 0, np.inf
            for seed in range(args.seeds):
                m = run_sim(RunConfig(scenario="paper", policy=policy, per=per, seed=seed)).metrics
                p95.append(m["p95_platooning_error_m"])
                coll += int(m["collisions"])
                gap = min(gap, m["min_gap_m"])
            print(
                f"| {policy} | {per:.1f} | {np.mean(p95):.3f} | {np.max(p95):.3f} | {coll} | {gap:.2f} |",
                flush=True,
            )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
