"""ConvoyEnv speed: parallel-env steps per second, printed as JSON.

Cases: the ``paper`` scenario (leader + 2 followers) and a 100-follower convoy, each with
fixed actions (the environment alone) and with every follower on the ``paper`` policy
(closed loop, what ``sim`` runs). Packet loss is on (PER 0.2, Bernoulli) so the channel's
cost is included. ``--profile`` adds where the time goes (cProfile, share of step time per
component). One process, one core.

    python benchmarks/bench_env.py [--seconds 3] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import platform
import pstats
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


def _make(n_followers: int, preset: str | None = None) -> tuple[ConvoyEnv, dict]:
    probe = load_policy("paper")
    env = ConvoyEnv(
        "paper",
        n_followers=n_followers,
        member_config=probe.member_config,
        control_rate_hz=probe.control_rate_hz,
        loss=LossConfig(per=0.2),
        vehicle_presets=None if preset is None else [preset] * (n_followers + 1),
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
    args = parser.parse_args()
    results = []
    for n_followers in args.followers:
        for closed_loop in (False, True):
            env, policies = _make(n_followers, args.vehicle_preset)
            pol = policies if closed_loop else None
            _run(env, pol, 0.2, 10**9)  # warm-up
            rates = []
            for _ in range(max(1, args.repeats)):
                steps, busy = _run(env, pol, args.seconds / max(1, args.repeats), 10**9)
                rates.append(steps / busy)
            best = max(rates)
            row = {
                "scenario": "paper",
                "vehicles": args.vehicle_preset or "scenario (1/10, 1/6)",
                "n_followers": n_followers,
                "actions": "paper policy" if closed_loop else "fixed",
                "loss": "bernoulli per=0.2",
                "repeats": len(rates),
                "env_steps_per_s": round(best, 1),
                "env_steps_per_s_median": round(float(np.median(rates)), 1),
                "vehicle_steps_per_s": round(best * (n_followers + 1), 1),
            }
            if args.profile:
                row["time_share"] = _profile(env, pol, max(50, min(2000, steps // 4)))
            results.append(row)
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
