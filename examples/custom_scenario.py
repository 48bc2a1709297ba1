"""A scenario of your own: an S-bend road with stop-and-go traffic ahead of the leader.

A scenario says who drives, where they start and what the leader does
(``openconvoy.envs.scenarios.Scenario``). ``PathScenario`` covers the common case: the leader
follows a ``Path`` (a polyline in the local ENU frame, metres) at a speed profile of time and
arc length. Here the paper's controller runs on it in ``ConvoyEnv`` at 20 % packet loss.

    python examples/custom_scenario.py [--seconds 60] [--per 0.2]
"""

from __future__ import annotations

import argparse
import copy
import math

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.core.spacing import SpacingConfig
from openconvoy.envs import ConvoyEnv
from openconvoy.envs.path import Path
from openconvoy.envs.scenarios import PathScenario
from openconvoy.envs.vehicles import VEHICLE_PRESETS
from openconvoy.policies.spec import load_policy


def s_bend(length_m: float = 400.0, amplitude_m: float = 8.0, wavelength_m: float = 80.0) -> Path:
    """A road east with gentle S-bends; it starts 100 m back so the convoy fits behind 0."""
    x = np.arange(-100.0, length_m, 0.5)
    y = np.where(x > 0.0, amplitude_m * np.sin(2 * math.pi * x / wavelength_m), 0.0)
    return Path(np.column_stack([x, y]))


def stop_and_go(t: float, s: float) -> float:
    """Leader speed (m/s): 2 m/s, a stop from 25 s to 30 s, then 1.5 m/s."""
    if t < 25.0:
        return 2.0
    if t < 30.0:
        return 0.0
    return 1.5


def make_scenario(seconds: float) -> PathScenario:
    small = (VEHICLE_PRESETS["1/10"], VEHICLE_PRESETS["1/6"])
    return PathScenario(
        "s-bend-stop-and-go",
        presets=[small[i % 2] for i in range(4)],  # leader + 3 followers
        path=s_bend(),
        speed_profile=stop_and_go,
        duration_s=seconds,
        spacing=SpacingConfig("constant-distance", distance_m=15.0),
        leader_start_s=100.0,  # arc length of the leader's start (x = 0)
    )


def run(seconds: float = 60.0, per: float = 0.2, seed: int = 0) -> dict[str, float]:
    """Run the paper's controller on the scenario; its p95 platooning error, min gap and
    collisions, from the environment's per-step infos."""
    policy = load_policy("paper")
    env = ConvoyEnv(
        make_scenario(seconds),
        member_config=policy.member_config,
        loss=LossConfig(per=per),
        control_rate_hz=float(policy.control_rate_hz),
    )
    policies = {a: copy.deepcopy(policy) for a in env.possible_agents}
    obs, _ = env.reset(seed=seed)
    for p in policies.values():
        p.reset(seed)
    errors, gaps, collided = [], [], False
    while env.agents:
        obs, _, _, _, infos = env.step({a: policies[a].act(obs[a]) for a in env.agents})
        for info in infos.values():
            errors.append(info["platooning_error_m"])
            gaps.append(info["gap_m"])
            collided |= bool(info["collision"])
    return {
        "p95_platooning_error_m": float(np.percentile(errors, 95)),
        "min_gap_m": float(np.min(gaps)),
        "collided": float(collided),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--per", type=float, default=0.2)
    args = parser.parse_args()
    for key, value in run(args.seconds, args.per).items():
        print(f"{key:<24}{value:.3f}")
