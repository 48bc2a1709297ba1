"""Where a fused ``VectorConvoyEnv`` tick spends its time: the stages of
``vector.step.fused_step`` called one by one in its order, each timed, over whole
stretches of an episode (one core; per-CPU-second figures are the process's CPU time).

Prints one JSON line per configuration: ns per tick and per env-step of each stage, the
Python wrapper around the fused call (``step`` minus ``fused_step``), and the fused call
itself. A stage's figure includes one compiled-call dispatch from Python (``dispatch``:
an empty kernel with as many arguments, measured alongside).

    python benchmarks/profile_vector_step.py [--ticks 600] [--case paper|long|long-la1]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"  # one core

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from openconvoy.comms.loss import LossConfig  # noqa: E402
from openconvoy.policies.spec import load_policy  # noqa: E402

CASES = {
    "paper": {"B": 1024, "vehicles": 3, "preset": "paper", "link_counters": "all"},
    "paper-4k": {"B": 4096, "vehicles": 3, "preset": "paper", "link_counters": "all"},
    "paper-16k": {"B": 16384, "vehicles": 3, "preset": "paper", "link_counters": "all"},
    "long": {"B": 1, "vehicles": 101, "preset": "paper", "link_counters": "all"},
    "long-la1": {"B": 1, "vehicles": 101, "preset": "cacc-lookahead1", "link_counters": "all"},
    "long-la1-kept": {
        "B": 1, "vehicles": 101, "preset": "cacc-lookahead1", "link_counters": "kept",
    },
}  # fmt: skip


def _env(case: dict):
    from openconvoy.envs import VectorConvoyEnv

    pol = load_policy(case["preset"])
    env = VectorConvoyEnv(
        case["B"], "paper", n_followers=case["vehicles"] - 1, member_config=pol.member_config,
        loss=LossConfig(per=0.2), link_counters=case["link_counters"],
    )  # fmt: skip
    env.reset(seed=0)
    return env


def _staged(env, act, bufs, clock_stages: dict) -> None:
    """``fused_step``'s body, stage by stage from Python, each stage timed."""
    from openconvoy.envs.vector.channel import _bernoulli_deliver, _tx_gate
    from openconvoy.envs.vector.leader import _drive, _project
    from openconvoy.envs.vector.measures import fill_infos, measure, reward
    from openconvoy.envs.vector.member import decide, lead_guard
    from openconvoy.envs.vector.observation import observe
    from openconvoy.envs.vector.plant import _plant_step

    (
        member,
        lead_project,
        lead_drive,
        guard,
        plant,
        clock,
        tx,
        deliver,
        view,
        meas,
        score,
        fill,
    ) = env._fused
    obs, rewards, fl, it, lf, li = bufs
    t, step_count, dt, max_steps, has_cmd, accel_old, own = clock
    pc = time.perf_counter_ns

    def timed(name, fn, *args):
        t0 = pc()
        fn(*args)
        clock_stages[name] = clock_stages.get(name, 0) + pc() - t0

    timed("decide", decide, act, *member)
    timed("leader", _project, *lead_project)
    timed("leader", _drive, *lead_drive)
    timed("leader", lead_guard, *guard)
    t0 = pc()
    has_cmd[:] = True
    accel_old[:] = own[4]
    clock_stages["numpy glue"] = clock_stages.get("numpy glue", 0) + pc() - t0
    timed("plant", _plant_step, *plant)
    t0 = pc()
    step_count += 1
    np.multiply(step_count, dt, out=t)
    clock_stages["numpy glue"] += pc() - t0
    timed("tx gate", _tx_gate, *tx)
    timed("loss+deliver", _bernoulli_deliver, *deliver)
    timed("observe", observe, obs, *view)
    timed("measure", measure, *meas)
    timed("reward", reward, rewards, *score)
    timed("fill infos", fill_infos, (fl, it, lf, li), *fill)


def profile(name: str, ticks: int) -> dict:
    from openconvoy.envs.vector.jit import bare_kernel
    from openconvoy.envs.vector.measures import info_arrays
    from openconvoy.envs.vector.step import fused_step

    @bare_kernel
    def _empty(*args):  # pragma: no cover - compiled
        return None

    case = CASES[name]
    B, V = case["B"], case["vehicles"]
    env = _env(case)
    act = np.tile(np.array([1.0, 0.0], np.float32), (B, V - 1, 1))
    obs = np.empty((B, V - 1, env.layout.size), dtype=np.float32)
    rewards = np.empty((B, V - 1))
    bufs = (obs, rewards, *info_arrays(B, V - 1))
    term, trunc = np.empty(B, dtype=bool), np.empty(B, dtype=bool)
    # Each configuration: a fresh env from seed 0, ``ticks`` ticks (no episode end).
    stages: dict[str, int] = {}
    for _ in range(3):  # compile or load every signature first
        _staged(env, act, bufs, stages)
        _empty(*env._fused[6])
        fused_step(act, obs, rewards, term, trunc, bufs[2:], env._fused)
        env.step(act)
    env = _env(case)
    stages.clear()
    c0 = time.process_time()
    for _ in range(ticks):
        _staged(env, act, bufs, stages)
    staged_cpu = time.process_time() - c0
    dispatch = 0
    deliver = env._fused[6]
    for _ in range(200):
        t0 = time.perf_counter_ns()
        _empty(*deliver)
        dispatch += time.perf_counter_ns() - t0
    env = _env(case)
    pc = time.perf_counter_ns
    fused_ns = 0
    c0 = time.process_time()
    for _ in range(ticks):
        t0 = pc()
        fused_step(act, obs, rewards, term, trunc, bufs[2:], env._fused)
        fused_ns += pc() - t0
    fused_cpu = time.process_time() - c0
    env = _env(case)
    step_ns = 0
    for _ in range(ticks):
        t0 = pc()
        env.step(act)
        step_ns += pc() - t0
    per_env = lambda ns: round(ns / ticks / B, 1)  # noqa: E731
    return {
        "case": name, "B": B, "vehicles": V, "ticks": ticks, "load_1min": os.getloadavg()[0],
        "ns_per_env_step": {k: per_env(v) for k, v in stages.items()},
        "dispatch_ns_per_call": round(dispatch / 200),
        "staged_cpu_s": round(staged_cpu, 3),
        "fused_ns_per_env_step": per_env(fused_ns),
        "fused_env_steps_per_cpu_s": round(ticks * B / fused_cpu),
        "step_ns_per_env_step": per_env(step_ns),
        "wrapper_ns_per_tick": round((step_ns - fused_ns) / ticks),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=600)
    ap.add_argument("--case", action="append", choices=sorted(CASES))
    args = ap.parse_args()
    for name in args.case or ["paper", "long"]:
        print(json.dumps(profile(name, args.ticks)), flush=True)


if __name__ == "__main__":
    main()
