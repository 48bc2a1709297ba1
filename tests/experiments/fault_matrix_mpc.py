"""The fault matrix of ``test_fault_matrix.py`` for the nine MPC presets, run outside the
suite (each run is its own ``ConvoyEnv``: 2,916 runs, ~18 min on two cores):

    python tests/experiments/fault_matrix_mpc.py

Prints progress and ``MPC fault matrix: N runs, K collided``; a collision is any two
convoy vehicles closer than their half lengths, any pair, any tick (as the suite's)."""

import math
import time
from concurrent.futures import ProcessPoolExecutor

SCEN = {
    "paper": (10.0, 40.0),
    "track": (10.0, 100.0),
    "emergency-braking": (3.0, 15.0),
    "highway-cut-in": (2.0, 8.0),
}
KINDS = ("halt", "silent", "dead")


def one(args):
    from openconvoy.experiments.runs import RunConfig, build_env

    scenario, policy, fault, per, seed, dur = args
    c = RunConfig(
        scenario=scenario, policy=policy, per=per, seed=seed, duration_s=dur, faults=(fault,)
    )
    env, policies = build_env(c)
    obs, _ = env.reset(seed=seed)
    for p in policies.values():
        p.reset(seed)
    L = [p.length_m for p in env.presets]
    worst = math.inf
    n = len(L)
    while env.agents:
        obs, *_ = env.step({a: policies[a].act(obs[a]) for a in env.agents})
        x, y = env.plant.x, env.plant.y
        for i in range(n):
            for j in range(i + 1, n):
                worst = min(worst, math.hypot(x[i] - x[j], y[i] - y[j]) - 0.5 * (L[i] + L[j]))
    return (scenario, policy, fault, per, seed, worst)


if __name__ == "__main__":
    from openconvoy.policies.presets import PRESETS

    mpc = [k for k, v in PRESETS.items() if v.mpc is not None]
    jobs = [
        (s, p, f"{k}:{v}@{t:g}", per, seed, d)
        for s, (t, d) in SCEN.items()
        for p in mpc
        for k in KINDS
        for v in range(3)
        for per in (0.0, 0.3, 0.6)
        for seed in (0, 1, 2)
    ]
    t0 = time.time()
    bad = []
    with ProcessPoolExecutor(2) as ex:
        for i, r in enumerate(ex.map(one, jobs, chunksize=4)):
            if r[-1] <= 0.0:
                bad.append(r)
                print("collided", r, flush=True)
            if i % 200 == 0:
                print(i, len(jobs), round(time.time() - t0), flush=True)
    print(
        f"MPC fault matrix: {len(jobs)} runs, {len(bad)} collided, {time.time() - t0:.0f} s",
        flush=True,
    )
