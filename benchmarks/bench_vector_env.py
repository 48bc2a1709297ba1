"""VectorConvoyEnv speed beside ConvoyEnv, printed as JSON lines (one process, one core).

Cases: the ``paper`` scenario (leader + 2 followers) at B = 1, 64, 1024 (and 16384 with
``--big``), and 10- and 100-vehicle convoys at B = 1 and 64, each with fixed actions under
Bernoulli loss (PER 0.2) with the ``paper`` member config (all-predecessors: O(N²) links);
100 and 1000 vehicles with ``lookahead:1`` (``cacc-lookahead1``'s member config), with
loss drawn on every pair and on the kept links only (``link_counters``); plus
the paper policy acting batched (``act_batch``) at B = 1024. ``ConvoyEnv`` runs the same configurations (B = 1:
it is one convoy; its env-steps/s do not grow with B). ``env_steps_per_s`` counts convoy
ticks, ``vehicle_steps_per_s`` vehicle ticks.

    python benchmarks/bench_vector_env.py [--seconds 2] [--big]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
from openconvoy.policies.spec import load_policy


def _timed(step, seconds: float) -> tuple[int, float]:
    n, t0 = 0, time.perf_counter()
    while True:
        step()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= seconds and n >= 3:
            return n, dt


def bench_vector(
    B: int,
    vehicles: int,
    seconds: float,
    policy: bool = False,
    preset: str = "paper",
    link_counters: str = "all",
) -> dict:
    pol = load_policy(preset)
    env = VectorConvoyEnv(
        B,
        "paper",
        n_followers=vehicles - 1,
        member_config=pol.member_config,
        loss=LossConfig(per=0.2),
        link_counters=link_counters,
    )
    obs, _ = env.reset(seed=0)
    fixed = np.tile(np.array([1.0, 0.0], np.float32), (B, vehicles - 1, 1))
    state = {"obs": obs}

    def step() -> None:
        actions = pol.act_batch(state["obs"]) if policy else fixed
        state["obs"] = env.step(actions)[0]

    n, dt = _timed(step, seconds)
    return {
        "world": "VectorConvoyEnv",
        "B": B,
        "vehicles": vehicles,
        "policy": preset if policy else "fixed",
        "topology": pol.member_config.topology,
        "link_counters": link_counters,
        "steps_per_s": round(n / dt, 1),
        "env_steps_per_s": round(n * B / dt),
        "vehicle_steps_per_s": round(n * B * vehicles / dt),
    }


def bench_single(vehicles: int, seconds: float, preset: str = "paper") -> dict:
    pol = load_policy(preset)
    env = ConvoyEnv(
        "paper", n_followers=vehicles - 1, member_config=pol.member_config, loss=LossConfig(per=0.2)
    )
    env.reset(seed=0)
    fixed = {a: np.array([1.0, 0.0], np.float32) for a in env.possible_agents}

    def step() -> None:
        if not env.agents:
            env.reset()
        env.step(fixed)

    n, dt = _timed(step, seconds)
    return {
        "world": "ConvoyEnv",
        "B": 1,
        "vehicles": vehicles,
        "policy": "fixed",
        "topology": pol.member_config.topology,
        "steps_per_s": round(n / dt, 1),
        "env_steps_per_s": round(n / dt),
        "vehicle_steps_per_s": round(n * vehicles / dt),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--big", action="store_true", help="also B = 16384")
    args = ap.parse_args()
    print(json.dumps({"python": platform.python_version(), "numpy": np.__version__}))
    sizes = [1, 64, 1024] + ([16384] if args.big else [])
    for vehicles in (3, 10, 100):
        print(json.dumps(bench_single(vehicles, args.seconds)), flush=True)
        for B in sizes if vehicles == 3 else [1, 64]:
            print(json.dumps(bench_vector(B, vehicles, args.seconds)), flush=True)
    # A bounded topology (lookahead:1): cost linear in N.
    for vehicles in (100, 1000):
        for counters in ("all", "kept"):
            print(
                json.dumps(
                    bench_vector(
                        1, vehicles, args.seconds, preset="cacc-lookahead1", link_counters=counters
                    )
                ),
                flush=True,
            )
    print(json.dumps(bench_single(100, args.seconds, preset="cacc-lookahead1")), flush=True)
    print(json.dumps(bench_vector(1024, 3, args.seconds, policy=True)), flush=True)


if __name__ == "__main__":
    main()
