"""Traffic speed: env steps per second of a 3-vehicle convoy in highway traffic, printed as JSON,
side by side with highway-env's own ``highway-v0`` in its multi-agent configuration.

Cases, for 10, 30 and 50 traffic cars on a 4-lane highway:

- ``openconvoy``: ``TrafficConvoyEnv("highway-cut-in:lanes=4,...")`` (the cut-in car counts
  as one of the traffic cars), leader + 2 followers, fixed actions (the environment alone),
  one step = one 0.05 s tick; with each traffic path (``HighwayConfig.road``): ``vector``
  (``VectorRoad``: highway-env's IDM/MOBIL on arrays, compiled by numba), ``vector_numpy``
  (the same road run as numpy calls, its fallback without numba), ``fast``
  (``FastRoad``: highway-env's vehicles, neighbour search and collision pre-check done once
  per step) and ``highway-env`` (its ``Road`` as is).
- ``highway-v0``: ``gymnasium.make("highway-v0")`` with 3 controlled vehicles
  (``MultiAgentAction`` of ``DiscreteMetaAction``, ``MultiAgentObservation`` of
  ``Kinematics``), ``vehicles_count`` traffic cars, ``simulation_frequency`` =
  ``policy_frequency`` = 20 Hz so one step is one 0.05 s tick as ours; and its default
  15 Hz / 1 Hz (15 simulation steps per env step) for reference.

An episode that ends (a collision, the time limit) is reset outside the timing. One
process, one core. Each case reports steps/s by wall clock and by the process's CPU time,
the ratio of ``vector`` to ``highway-v0`` (20 Hz) in the same minutes, and the 1-minute load
average (the machine is shared).

    python benchmarks/bench_traffic.py [--seconds 3] [--counts 10,30,50]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np


def _time_steps(step, reset, seconds: float) -> tuple[float, float]:
    """Steps per second of ``step()`` over about ``seconds`` s of wall time, by wall clock
    and by this process's CPU time (which counts only while the process runs, so it
    says less about the machine's load; resets not counted)."""
    reset()
    steps, busy, cpu = 0, 0.0, 0.0
    while busy < seconds:
        t0, c0 = time.perf_counter(), time.process_time()
        done = step()
        busy += time.perf_counter() - t0
        cpu += time.process_time() - c0
        steps += 1
        if done:
            reset()
    return steps / busy, steps / cpu


def bench_openconvoy(count: int, road: str, seconds: float) -> tuple[float, float]:
    from openconvoy.envs.traffic.env import TrafficConvoyEnv
    from openconvoy.envs.traffic.road import VectorRoad

    compiled = VectorRoad.compiled
    if road == "vector_numpy":
        road, VectorRoad.compiled = "vector", False
    spec = f"highway-cut-in:lanes=4,traffic={count - 1},duration_s=60,road={road}"
    env = TrafficConvoyEnv(spec)
    env.reset(seed=0)  # (a first step compiles or loads the kernels: not timed)
    env.step({a: np.array([25.0, 0.0], dtype=np.float32) for a in env.agents})
    action = np.array([25.0, 0.0], dtype=np.float32)
    seed = [0]

    def reset() -> None:
        env.reset(seed=seed[0])
        seed[0] += 1

    def step() -> bool:
        env.step({a: action for a in env.agents})
        return not env.agents

    try:
        return _time_steps(step, reset, seconds)
    finally:
        VectorRoad.compiled = compiled


def bench_highway_v0(
    count: int, sim_hz: int, policy_hz: int, seconds: float
) -> tuple[float, float]:
    import gymnasium
    import highway_env  # noqa: F401  (registers highway-v0)

    env = gymnasium.make(
        "highway-v0",
        config={
            "controlled_vehicles": 3,
            "vehicles_count": count,
            "lanes_count": 4,
            "simulation_frequency": sim_hz,
            "policy_frequency": policy_hz,
            "duration": 10_000,
            "action": {"type": "MultiAgentAction", "action_config": {"type": "DiscreteMetaAction"}},
            "observation": {
                "type": "MultiAgentObservation",
                "observation_config": {"type": "Kinematics"},
            },
        },
    )
    idle = (1, 1, 1)  # DiscreteMetaAction IDLE for each controlled vehicle
    seed = [0]

    def reset() -> None:
        env.reset(seed=seed[0])
        seed[0] += 1

    def step() -> bool:
        _, _, term, trunc, _ = env.step(idle)
        return bool(term or trunc)

    return _time_steps(step, reset, seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per case")
    parser.add_argument("--counts", default="10,30,50", help="traffic car counts")
    args = parser.parse_args()
    counts = [int(c) for c in args.counts.split(",")]
    rows = []
    for n in counts:
        row: dict = {"traffic_cars": n}
        cases = {
            "openconvoy_vector": (bench_openconvoy, (n, "vector")),
            "openconvoy_vector_numpy": (bench_openconvoy, (n, "vector_numpy")),
            "openconvoy_fast": (bench_openconvoy, (n, "fast")),
            "openconvoy_highway_env_road": (bench_openconvoy, (n, "highway-env")),
            "highway_v0_20hz": (bench_highway_v0, (n, 20, 20)),
            "highway_v0_default_15hz_1hz": (bench_highway_v0, (n, 15, 1)),
        }
        for name, (bench, case) in cases.items():
            wall, cpu = bench(*case, args.seconds)
            row[f"{name}_steps_per_s"] = round(wall, 1)
            row[f"{name}_cpu_steps_per_s"] = round(cpu, 1)
        row["vector_over_highway_v0_20hz"] = round(
            row["openconvoy_vector_steps_per_s"] / row["highway_v0_20hz_steps_per_s"], 1
        )
        row["load_average_1min"] = os.getloadavg()[0]
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(
        json.dumps(
            {
                "benchmark": "traffic",
                "convoy": "leader + 2 followers, full-size, fixed actions",
                "tick_s": 0.05,
                "python": platform.python_version(),
                "machine": platform.machine(),
                "rows": rows,
            }
        )
    )


if __name__ == "__main__":
    main()
