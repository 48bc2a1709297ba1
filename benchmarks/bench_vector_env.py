"""VectorConvoyEnv beside ConvoyEnv, one process on one core: a JSON line per case, then
the side-by-side table (issue 14).

Cases: the ``paper`` scenario (leader + 2 followers, the ``paper`` member config:
all-predecessors) at B = 1, 64, 1,024 and 16,384 with fixed actions, and at B = 1,024
with the paper policy acting batched (``act_batch``); 100-follower convoys at B = 1
(all-predecessors, and ``lookahead:1`` = ``cacc-lookahead1``'s member config) and a
1,000-follower ``lookahead:1`` convoy, with loss drawn on every pair (``ConvoyEnv``'s
counters) and on the kept links only (``link_counters="kept"``). Bernoulli loss, PER 0.2.
``ConvoyEnv`` runs the same configurations (it is one convoy: its rate does not grow
with B). Then the paper scenario at B = 1,024 beside ``ConvoyEnv`` with PER 0.2 alone, with
latency 0.12 s, latency 0.12 s + jitter 0.1 s, and GPS noise 0.3 m (a table of their own:
``fused`` says whether VectorConvoyEnv ran its one fused kernel or stepped stage by
stage). Rates per wall second and per CPU second of this process (``process_time``:
steadier on a shared machine); ``env_steps`` count convoy ticks, ``vehicle_steps``
vehicle ticks. The first VectorConvoyEnv case also reports the kernels' load (or
compile) time.

    python benchmarks/bench_vector_env.py [--seconds 2] [--small] [--channel]
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


def bench_channel(world, B, seconds, latency_s=0.0, jitter_s=0.0, gps_noise_m=0.0):
    """The paper scenario with fixed actions and PER 0.2 as above, plus latency, jitter
    (uniform extra delay, s) or GPS noise (m): cases VectorConvoyEnv steps stage by stage
    (``fused``: whether it ran its one fused kernel instead)."""
    from openconvoy.envs import VectorConvoyEnv

    pol = load_policy("paper")
    kw = {
        "n_followers": 2, "member_config": pol.member_config, "gps_noise_m": gps_noise_m,
        "loss": LossConfig(per=0.2, latency_s=latency_s, jitter_s=jitter_s),
    }  # fmt: skip
    env = VectorConvoyEnv(B, "paper", **kw) if world == "vector" else ConvoyEnv("paper", **kw)
    env.reset(seed=0)
    fused = getattr(env, "_fused", None) is not None
    if world == "vector":
        fixed = np.tile(np.array([1.0, 0.0], np.float32), (B, 2, 1))
        step = lambda: env.step(fixed)  # noqa: E731
    else:
        acts = {a: np.array([1.0, 0.0], np.float32) for a in env.possible_agents}

        def step() -> None:
            if not env.agents:
                env.reset()
            env.step(acts)

    step()
    n, wall, cpu = _timed(step, seconds)
    channel = [f"latency {latency_s:g} s"] if latency_s else []
    channel += [f"jitter {jitter_s:g} s"] if jitter_s else []
    channel += [f"GPS noise {gps_noise_m:g} m"] if gps_noise_m else []
    return {
        "world": "VectorConvoyEnv" if world == "vector" else "ConvoyEnv", "B": B, "vehicles": 3,
        "policy": "fixed", "topology": pol.member_config.topology, "link_counters": "all",
        "channel": " + ".join(channel) or "nothing", "fused": fused, **_rates(n, wall, cpu, B, 3),
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
    # PER 0.2 alone, then with latency, jitter and GPS noise, each beside ConvoyEnv.
    channels = ({}, {"latency_s": 0.12}, {"latency_s": 0.12, "jitter_s": 0.1}, {"gps_noise_m": 0.3})
    for extra in channels:
        out += [("channel", {"world": "single", "B": 1, **extra})]
        out += [("channel", {"world": "vector", "B": 1024, **extra})]
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


def _channel_table(rows: list[dict]) -> str:
    """The latency / jitter / GPS-noise cases (paper scenario, 3 vehicles, PER 0.2)."""
    lines = [
        "\n| world | B | on top of PER 0.2 | stepping | env-steps/s | vehicle-steps/s "
        "| per CPU-s: env-steps | vehicle-steps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        how = "fused" if r["fused"] else "staged" if r["world"] != "ConvoyEnv" else "per vehicle"
        lines.append(
            f"| {r['world']} | {r['B']:,} | {r['channel']} | {how} "
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
    ap.add_argument(
        "--channel", action="store_true", help="only the latency / jitter / GPS-noise cases"
    )
    args = ap.parse_args()
    load = os.getloadavg()[0]
    print(
        json.dumps(
            {"python": platform.python_version(), "numpy": np.__version__, "load_1min": load}
        )
    )
    rows = []
    cases = [c for c in _cases(args.small) if c[0] == "channel" or not args.channel]
    for kind, kw in cases:
        bench = {"single": bench_single, "vector": bench_vector, "channel": bench_channel}[kind]
        row = bench(seconds=args.seconds, **kw)
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(f"\nload average (1 min) at start {load:.2f}, at end {os.getloadavg()[0]:.2f}\n")
    for table, mine in ((_table, False), (_channel_table, True)):
        if any(("channel" in r) == mine for r in rows):
            print(table([r for r in rows if ("channel" in r) == mine]))


if __name__ == "__main__":
    main()
