"""ConvoyEnv speed: parallel-env steps per second, printed as JSON.

Cases: the ``paper`` scenario (leader + 2 followers) and a 100-follower convoy, each with
fixed actions (the environment alone) and with every follower on the ``paper`` policy
(closed loop, what ``sim`` runs). Packet loss is on (PER 0.2, Bernoulli) so the channel's
cost is included. Each case runs on both of ``ConvoyEnv``'s backends (``envs.compiled``:
the compiled tick and the Python path), their timed runs alternating, and prints the
ratio. ``--long N`` adds a convoy of N all-predecessor followers: the seconds to
construct and to reset it and the memory that takes (peak RSS growth, MB), each backend
in a fresh process.
``--profile`` adds where the time goes (cProfile, share of step time per component).
One process, one core.

    python benchmarks/bench_env.py [--seconds 3] [--profile] [--long 1000]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import multiprocessing
import platform
import pstats
import resource
import time

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.envs import ConvoyEnv
from openconvoy.policies.spec import load_policy

COMPONENTS = {
    "member.observation": ("core/member.py", "observation"),
    "member.supervise": ("core/member.py", "supervise"),
    "member.receive": ("core/member.py", "receive"),
    "member.wants_to_send": ("core/member.py", "wants_to_send"),
    "plant.step": ("envs/plant.py", "step"),
    "channel.send+deliver": (("envs/channel.py", "send"), ("envs/channel.py", "deliver")),
    "scenario.leader_command": ("envs/scenarios.py", "leader_command"),
    "reward": ("envs/reward.py", "reward"),
    "infos": ("envs/convoy_env.py", "_infos"),
    "policy.act": ("policies/classical.py", "act"),
}


BACKENDS = ("python", "compiled")


def _make(n_followers: int, preset: str | None, backend: str) -> tuple[ConvoyEnv, dict]:
    probe = load_policy("paper")
    env = ConvoyEnv(
        "paper",
        n_followers=n_followers,
        member_config=probe.member_config,
        control_rate_hz=probe.control_rate_hz,
        loss=LossConfig(per=0.2),
        vehicle_presets=None if preset is None else [preset] * (n_followers + 1),
        backend=backend,
    )
    policies = {a: load_policy("paper") for a in env.possible_agents}
    return env, policies


def _run(
    env: ConvoyEnv, policies: dict | None, seconds: float, max_steps: int
) -> tuple[int, float]:
    """Step (resetting at episode ends, reset time excluded) for ``seconds``; (steps, s)."""
    fixed = {a: np.array([1.0, 0.0], dtype=np.float32) for a in env.possible_agents}
    steps, busy, seed = 0, 0.0, 0
    obs, _ = env.reset(seed=seed)
    while busy < seconds and steps < max_steps:
        t0 = time.perf_counter()
        chunk = 0
        while env.agents and chunk < 200:
            if policies is None:
                actions = fixed
            else:
                actions = {a: policies[a].act(obs[a]) for a in env.agents}
            obs, *_ = env.step(actions)
            chunk += 1
        busy += time.perf_counter() - t0
        steps += chunk
        if not env.agents:
            seed += 1
            obs, _ = env.reset(seed=seed)
    return steps, busy


def _profile(env: ConvoyEnv, policies: dict | None, steps: int) -> dict[str, float]:
    prof = cProfile.Profile()
    prof.enable()
    _run(env, policies, 1e9, steps)
    prof.disable()
    stats = pstats.Stats(prof).stats  # {(file, line, func): (cc, nc, tt, ct, callers)}
    total = sum(tt for (_, _, _), (_, _, tt, _, _) in stats.items())

    def cum(file: str, func: str) -> float:
        return sum(
            ct for (f, _, fn), (_, _, _, ct, _) in stats.items() if f.endswith(file) and fn == func
        )

    out = {}
    for name, spec in COMPONENTS.items():
        specs = spec if isinstance(spec[0], tuple) else (spec,)
        out[name] = round(sum(cum(f, fn) for f, fn in specs) / total, 3)
    out["env total (step)"] = round(cum("envs/convoy_env.py", "step") / total, 3)
    return out


def _construct_and_reset(n_followers: int, backend: str, out: multiprocessing.Queue) -> None:
    """In a fresh process: seconds to construct and reset ``n_followers`` all-predecessor
    followers, and the peak RSS growth (MB) over a process that built a 2-follower env."""
    ConvoyEnv("paper", backend=backend).reset(seed=0)  # imports, kernels loaded
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    env = ConvoyEnv("paper", n_followers=n_followers, loss=LossConfig(per=0.2), backend=backend)
    t1 = time.perf_counter()
    env.reset(seed=0)
    t2 = time.perf_counter()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    out.put((t1 - t0, t2 - t1, (rss - rss0) / 1024))


def _long(n_followers: int, backend: str) -> dict:
    """``_construct_and_reset`` of one backend, as a result row."""
    ctx = multiprocessing.get_context("spawn")
    q: multiprocessing.Queue = ctx.Queue()
    p = ctx.Process(target=_construct_and_reset, args=(n_followers, backend, q))
    p.start()
    construct_s, reset_s, mb = q.get()
    p.join()
    return {
        "case": "long platoon",
        "topology": "all-predecessors",
        "n_followers": n_followers,
        "backend": backend,
        "construct_s": round(construct_s, 3),
        "reset_s": round(reset_s, 3),
        "peak_rss_growth_mb": round(mb, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per case")
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="timed runs per case; the best is reported (shared machines are noisy)",
    )
    parser.add_argument(
        "--followers",
        type=int,
        nargs="+",
        default=[2, 100],
        help="convoy sizes to time (followers)",
    )
    parser.add_argument("--profile", action="store_true", help="add a cProfile breakdown")
    parser.add_argument(
        "--vehicle-preset",
        metavar="PRESET",
        help="every vehicle this preset (default: the scenario's lag presets), "
        "e.g. ardupilot-rover for the autopilot's PI speed loop",
    )
    parser.add_argument(
        "--long", type=int, metavar="N", help="time constructing and resetting N followers"
    )
    args = parser.parse_args()
    results = []
    for n_followers in args.followers:
        for closed_loop in (False, True):
            row = {
                "scenario": "paper",
                "vehicles": args.vehicle_preset or "scenario (1/10, 1/6)",
                "n_followers": n_followers,
                "actions": "paper policy" if closed_loop else "fixed",
                "loss": "bernoulli per=0.2",
                "repeats": max(1, args.repeats),
            }
            made = {b: _make(n_followers, args.vehicle_preset, b) for b in BACKENDS}
            rates: dict[str, list[float]] = {b: [] for b in BACKENDS}
            cpu_rates: dict[str, list[float]] = {b: [] for b in BACKENDS}
            for env, policies in made.values():
                _run(env, policies if closed_loop else None, 0.2, 10**9)  # warm-up
            for _ in range(max(1, args.repeats)):  # alternating: the same load on both
                for b, (env, policies) in made.items():
                    pol = policies if closed_loop else None
                    cpu0 = time.process_time()
                    steps, busy = _run(env, pol, args.seconds / max(1, args.repeats), 10**9)
                    rates[b].append(steps / busy)
                    cpu_rates[b].append(steps / (time.process_time() - cpu0))
            for b in BACKENDS:
                best = max(rates[b])
                row[b] = {
                    "env_steps_per_s": round(best, 1),
                    "env_steps_per_s_median": round(float(np.median(rates[b])), 1),
                    # per second of this process's CPU time (resets included): what a
                    # core of its own would give on a shared machine
                    "env_steps_per_cpu_s": round(max(cpu_rates[b]), 1),
                    "vehicle_steps_per_s": round(best * (n_followers + 1), 1),
                }
            row["compiled_over_python"] = round(
                row["compiled"]["env_steps_per_s"] / row["python"]["env_steps_per_s"], 2
            )
            if args.profile:
                env, policies = made["python"]
                pol = policies if closed_loop else None
                row["time_share_python"] = _profile(env, pol, 2000)
            results.append(row)
    if args.long:
        for b in BACKENDS:
            results.append(_long(args.long, b))
    print(
        json.dumps(
            {
                "benchmark": "bench_env",
                "python": platform.python_version(),
                "machine": platform.machine(),
                "processor": platform.processor() or platform.machine(),
                "results": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
