"""Traffic speed: env steps per second of a 3-vehicle convoy in highway traffic, printed as JSON,
side by side with highway-env's own ``highway-v0`` in its multi-agent configuration.

Cases, for 10, 30 and 50 traffic cars on a 4-lane highway:

- ``openconvoy``: ``TrafficConvoyEnv("highway-cut-in:lanes=4,...")`` (the cut-in car counts
  as one of the traffic cars), leader + 2 followers, fixed actions (the environment alone),
  one step = one 0.05 s tick; with each traffic path (``HighwayConfig.road``): ``vector``
  (``VectorRoad``: highway-env's IDM/MOBIL for all cars at once with numpy), ``fast``
  (``FastRoad``: highway-env's vehicles, neighbour search and collision pre-check done once
  per step) and ``highway-env`` (its ``Road`` as is).
- ``highway-v0``: ``gymnasium.make("highway-v0")`` with 3 controlled vehicles
  (``MultiAgentAction`` of ``DiscreteMetaAction``, ``MultiAgentObservation`` of
  ``Kinematics``), ``vehicles_count`` traffic cars, ``simulation_frequency`` =
  ``policy_frequency`` = 20 Hz so one step is one 0.05 s tick as ours; and its default
  15 Hz / 1 Hz (15 simulation steps per env step) for reference.

An episode that ends (a collision, the time limit) is reset outside the timing. One
process, one core.

    python benchmarks/bench_traffic.py [--seconds 3] [--counts 10,30,50]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np


def _time_steps(step, reset, seconds: float) -> float:
    """Steps per second of ``step()`` over about ``seconds`` s (resets not counted)."""
    reset()
    steps, busy = 0, 0.0
    while busy < seconds:
        t0 = time.perf_counter()
        done = step()
        busy += time.perf_counter() - t0
        steps += 1
        if done:
            reset()
    return steps / busy


def bench_openconvoy(count: int, road: str, seconds: float) -> float:
    from openconvoy.envs.traffic_env import TrafficConvoyEnv

    spec = f"highway-cut-in:lanes=4,traffic={count - 1},duration_s=60,road={road}"
    env = TrafficConvoyEnv(spec)
    action = np.array([25.0, 0.0], dtype=np.float32)
    seed = [0]

    def reset() -> None:
        env.reset(seed=seed[0])
        seed[0] += 1

    def step() -> bool:
        env.step({a: action for a in env.agents})
        return not env.agents

    return _time_steps(step, reset, seconds)


def bench_highway_v0(count: int, sim_hz: int, policy_hz: int, seconds: float) -> float:
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
        rows.append(
            {
                "traffic_cars": n,
                "openconvoy_vector_steps_per_s": round(
                    bench_openconvoy(n, "vector", args.seconds), 1
                ),
                "openconvoy_fast_steps_per_s": round(bench_openconvoy(n, "fast", args.seconds), 1),
                "openconvoy_highway_env_road_steps_per_s": round(
                    bench_openconvoy(n, "highway-env", args.seconds), 1
                ),
                "highway_v0_20hz_steps_per_s": round(bench_highway_v0(n, 20, 20, args.seconds), 1),
                "highway_v0_default_15hz_1hz_steps_per_s": round(
                    bench_highway_v0(n, 15, 1, args.seconds), 1
                ),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
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
