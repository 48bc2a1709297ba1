"""A PER sweep of the ``paper`` policy in one batched run: every (PER, seed) is a convoy.

7 PERs (0 to 0.6) × ``--seeds`` seeds of the 60 s paper scenario in one
``VectorConvoyEnv`` (Bernoulli loss, one PER per convoy), the policy acting through
``act_batch``. Prints JSON: the wall time, and per PER the pooled 95th-percentile
platooning error (|gap − desired gap| over every follower and tick, reset tick and final
tick included, as a run's log has them), collisions and delivery ratio. Each convoy is
the run ``experiment per-sweep`` makes for that PER and seed (same seeds, bit-equal
states; ``tests/envs/test_vector_env.py``); the sweep's own metrics are computed from
its written CSV logs, so its digits may differ in the last places.

    python benchmarks/bench_vector_sweep.py [--seeds 100]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.envs import VectorConvoyEnv
from openconvoy.policies.spec import load_policy

PERS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    args = ap.parse_args()
    start = time.perf_counter()
    policy = load_policy("paper")
    runs = [(per, seed) for per in PERS for seed in range(args.seeds)]
    env = VectorConvoyEnv(
        len(runs),
        "paper",
        member_config=policy.member_config,
        control_rate_hz=policy.control_rate_hz,
        loss=[LossConfig(per=per) for per, _ in runs],
        autoreset=False,
    )
    obs, info = env.reset(seed=[seed for _, seed in runs])
    errors = [info["platooning_error_m"]]
    alive = np.ones(len(runs), dtype=bool)
    collided = np.zeros(len(runs), dtype=bool)
    for _ in range(env.max_steps):
        obs, _, term, _, info = env.step(policy.act_batch(obs))
        errors.append(np.where(alive[:, None], info["platooning_error_m"], np.nan))
        collided |= term & alive
        alive &= ~term
    err = np.stack(errors, axis=1)  # (runs, ticks, followers)
    delivered = info["msgs_received"].sum(axis=1)
    lost = info["msgs_lost"].sum(axis=1)
    wall = time.perf_counter() - start
    per_arr = np.array([p for p, _ in runs])
    rows = []
    for per in PERS:
        sel = per_arr == per
        p95 = [float(np.nanpercentile(e, 95.0)) for e in err[sel]]
        ratio = delivered[sel] / np.maximum(delivered[sel] + lost[sel], 1)
        rows.append(
            {
                "per": per,
                "p95_platooning_error_m_mean": round(float(np.mean(p95)), 4),
                "p95_platooning_error_m_max": round(float(np.max(p95)), 4),
                "collisions": int(collided[sel].sum()),
                "delivery_ratio_mean": round(float(np.mean(ratio)), 4),
            }
        )
    print(
        json.dumps(
            {"runs": len(runs), "ticks": env.max_steps + 1, "wall_s": round(wall, 1), "rows": rows}
        )
    )


if __name__ == "__main__":
    main()
