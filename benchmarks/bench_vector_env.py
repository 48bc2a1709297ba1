"""VectorConvoyEnv beside ConvoyEnv, one process on one core: a JSON line per case, then
the side-by-side table (issue 14).

Cases: the ``paper`` scenario (leader + 2 followers, the ``paper`` member config:
all-predecessors) at B = 1, 64, 1,024 and 16,384 with fixed actions, and at B = 1,024
with the paper policy acting batched (``act_batch``); 100-follower convoys at B = 1
(all-predecessors, and ``lookahead:1`` = ``cacc-lookahead1``'s member config) and a
1,000-follower ``lookahead:1`` convoy, with loss drawn on every pair (``ConvoyEnv``'s
counters) and on the kept links only (``link_counters="kept"``). Bernoulli loss, PER 0.2.
``ConvoyEnv`` runs the same configurations (it is one convoy: its rate does not grow
with B). Rates per wall second and per CPU second of this process (``process_time``:
steadier on a shared machine); ``env_steps`` count convoy ticks, ``vehicle_steps``
vehicle ticks. The first VectorConvoyEnv case also reports the kernels' load (or
compile) time.

    python benchmarks/bench_vector_env.py [--seconds 2] [--small]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"  # one core

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from openconvoy.comms.loss import LossConfig  # noqa: E402
from openconvoy.envs import ConvoyEnv  # noqa: E402
from openconvoy.policies.spec import load_policy  # noqa: E402


def _timed(step, seconds: float) -> tuple[int, float, float]:
    """Steps run, wall seconds, CPU seconds."""
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while True:
        step()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= seconds and n >= 3:
            return n, dt, time.process_time() - c0


def _sig(x: float) -> float:
    """Whole numbers from 100 up, three significant digits below."""
    return round(x) if x >= 100 else float(f"{x:.3g}")


def _rates(n: int, wall: float, cpu: float, B: int, vehicles: int) -> dict:
    return {
        "env_steps_per_s": _sig(n * B / wall),
        "vehicle_steps_per_s": _sig(n * B * vehicles / wall),
        "env_steps_per_cpu_s": _sig(n * B / cpu),
        "vehicle_steps_per_cpu_s": _sig(n * B * vehicles / cpu),
    }


def bench_vector(B, vehicles, seconds, preset="paper", policy=False, link_counters="all"):
    from openconvoy.envs import VectorConvoyEnv

    pol = load_policy(preset)
    t0 = time.perf_counter()
    env = VectorConvoyEnv(
        B, "paper", n_followers=vehicles - 1, member_config=pol.member_config,
        loss=LossConfig(per=0.2), link_counters=link_counters,
    )  # fmt: skip
    obs, _ = env.reset(seed=0)
    env.step(np.zeros((B, vehicles - 1, 2), np.float32))
    setup = time.perf_counter() - t0
    fixed = np.tile(np.array([1.0, 0.0], np.float32), (B, vehicles - 1, 1))
    state = {"obs": obs}

    def step() -> None:
        actions = pol.act_batch(state["obs"]) if policy else fixed
        state["obs"] = env.step(actions)[0]

    n, wall, cpu = _timed(step, seconds)
    return {
        "world": "VectorConvoyEnv", "B": B, "vehicles": vehicles,
        "policy": preset if policy else "fixed", "topology": pol.member_config.topology,
        "link_counters": link_counters, "setup_s": round(setup, 2),
        **_rates(n, wall, cpu, B, vehicles),
    }  # fmt: skip


def bench_single(vehicles, seconds, preset="paper", policy=False):
    pol = load_policy(preset)
    env = ConvoyEnv(
        "paper", n_followers=vehicles - 1, member_config=pol.member_config, loss=LossConfig(per=0.2)
    )
    obs, _ = env.reset(seed=0)
    agents = env.possible_agents
    pols = {a: load_policy(preset) for a in agents}
    state = {"obs": obs}

    def step() -> None:
        if not env.agents:
            state["obs"] = env.reset()[0]
        if policy:
            acts = {a: pols[a].act(state["obs"][a]) for a in agents}
        else:
            acts = {a: np.array([1.0, 0.0], np.float32) for a in agents}
        state["obs"] = env.step(acts)[0]

    n, wall, cpu = _timed(step, seconds)
    return {
        "world": "ConvoyEnv", "B": 1, "vehicles": vehicles,
        "policy": preset if policy else "fixed", "topology": pol.member_config.topology,
        "link_counters": "all", **_rates(n, wall, cpu, 1, vehicles),
    }  # fmt: skip


def _cases(small: bool) -> list[tuple[str, dict]]:
    sizes = [1, 64, 1024] + ([] if small else [16384])
    out = [("single", {"vehicles": 3})]
    out += [("vector", {"B": B, "vehicles": 3}) for B in sizes]
    out += [("single", {"vehicles": 3, "policy": True})]
    out += [("vector", {"B": 1024, "vehicles": 3, "policy": True})]
    out += [("single", {"vehicles": 101}), ("vector", {"B": 1, "vehicles": 101})]
    for vehicles in (101, 1001):
        la = {"vehicles": vehicles, "preset": "cacc-lookahead1"}
        out += [("single", la)] if vehicles == 101 or not small else []
        out += [("vector", {"B": 1, **la}), ("vector", {"B": 1, **la, "link_counters": "kept"})]
    return out


def _table(rows: list[dict]) -> str:
    lines = [
        "| world | B | vehicles | topology | policy | loss on | env-steps/s | vehicle-steps/s "
        "| per CPU-s: env-steps | vehicle-steps |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['world']} | {r['B']:,} | {r['vehicles']:,} | {r['topology']} | {r['policy']} "
            f"| {'kept links' if r['link_counters'] == 'kept' else 'all pairs'} "
            f"| {r['env_steps_per_s']:,} | {r['vehicle_steps_per_s']:,} "
            f"| {r['env_steps_per_cpu_s']:,} | {r['vehicle_steps_per_cpu_s']:,} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument(
        "--small", action="store_true", help="skip B = 16384 and 1000-vehicle ConvoyEnv"
    )
    args = ap.parse_args()
    load = os.getloadavg()[0]
    print(
        json.dumps(
            {"python": platform.python_version(), "numpy": np.__version__, "load_1min": load}
        )
    )
    rows = []
    for kind, kw in _cases(args.small):
        row = (bench_single if kind == "single" else bench_vector)(seconds=args.seconds, **kw)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(f"\nload average (1 min) at start {load:.2f}, at end {os.getloadavg()[0]:.2f}\n")
    print(_table(rows))


if __name__ == "__main__":
    main()
