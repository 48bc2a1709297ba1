"""Per-car MPC solve time: p50 / p99 at H = 10 / 20 / 40 with 3 / 10 / 30 vehicles (issue 24).

Runs the ``paper`` scenario (straight road, the leader's 1 -> 2 -> 1 m/s profile) with
``paper-mpc`` (all predecessors, shared plans, DAQP) for ``--duration`` seconds per cell,
on one core (``sched_setaffinity``), and times every follower's whole ``act`` (reading the
targets and plans, building the dense QP, solving it) and, separately, the QP solve alone
(``core.mpc.solve``), each in wall-clock time and in the thread's CPU time
(``time.thread_time``: what the computation costs, without the time other processes held
the core — on a loaded machine wall-clock percentiles measure the scheduler). Prints one
row per (H, vehicles) and the load average::

    python benchmarks/bench_mpc.py [--duration 10] [--solver daqp|osqp]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np

from openconvoy.core import mpc as core_mpc
from openconvoy.envs.plans import PlanRelay
from openconvoy.experiments.runs import ConvoySection, RunConfig, build_env
from openconvoy.policies import mpc as policy_mpc
from openconvoy.policies.presets import PRESETS

Times = dict[str, list[float]]


def cell(horizon: int, vehicles: int, duration_s: float, solver: str) -> Times:
    """Wall and CPU times (s) of every follower's act and solve, every tick."""
    base = PRESETS["paper-mpc"]
    assert base.mpc is not None
    name = f"bench-mpc-{horizon}"
    PRESETS[name] = dataclasses.replace(
        base, name=name, mpc=dataclasses.replace(base.mpc, horizon=horizon, solver=solver)
    )
    times: Times = {"act": [], "act_cpu": [], "solve": [], "solve_cpu": []}
    real_solve = core_mpc.solve

    def timed_solve(qp: core_mpc.QP, which: str = "daqp") -> core_mpc.Solution:
        t0, c0 = time.perf_counter(), time.thread_time()
        out = real_solve(qp, which)
        times["solve_cpu"].append(time.thread_time() - c0)
        times["solve"].append(time.perf_counter() - t0)
        return out

    policy_mpc.solve = timed_solve  # type: ignore[assignment]
    try:
        config = RunConfig(
            scenario="paper",
            policy=name,
            duration_s=duration_s,
            convoy=ConvoySection(n_followers=vehicles - 1),
        )
        env, policies = build_env(config)
        relay = PlanRelay(env, policies)
        obs, _ = env.reset(seed=0)
        while env.agents:
            relay.before_act()
            actions = {}
            for a in env.agents:
                t0, c0 = time.perf_counter(), time.thread_time()
                actions[a] = policies[a].act(obs[a])
                times["act_cpu"].append(time.thread_time() - c0)
                times["act"].append(time.perf_counter() - t0)
            relay.after_act()
            obs, *_ = env.step(actions)
    finally:
        policy_mpc.solve = real_solve  # type: ignore[assignment]
        PRESETS.pop(name)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=10.0, help="simulated seconds per cell")
    ap.add_argument("--solver", default="daqp", choices=("daqp", "osqp"))
    ap.add_argument("--horizons", default="10,20,40")
    ap.add_argument("--vehicles", default="3,10,30")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    print(f"load average before: {os.getloadavg()}; solver {args.solver}; one core")
    print(
        "| H | vehicles | solve CPU p50 / p99 (us) | act CPU p50 / p99 (us) "
        "| solve wall p50 / p99 (us) | act wall p50 / p99 (us) | solves |"
    )
    print("|---|---|---|---|---|---|---|")
    for h in (int(x) for x in args.horizons.split(",")):
        for n in (int(x) for x in args.vehicles.split(",")):
            t = {k: np.array(v) * 1e6 for k, v in cell(h, n, args.duration, args.solver).items()}

            def pp(k: str, t: dict[str, np.ndarray] = t) -> str:
                return f"{np.percentile(t[k], 50):.0f} / {np.percentile(t[k], 99):.0f}"

            print(
                f"| {h} | {n} | {pp('solve_cpu')} | {pp('act_cpu')} | {pp('solve')} "
                f"| {pp('act')} | {len(t['solve'])} |",
                flush=True,
            )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
