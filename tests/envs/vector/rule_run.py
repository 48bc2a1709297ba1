"""Both worlds on one run, for ``test_rules``: ``ConvoyEnv`` and ``VectorConvoyEnv`` under
the constant-time-headway spacing, the ``paper`` policy acting on the batched observations
and both worlds taking those actions. Asserts the two agree at every tick (plant within
1e-9 m, desired gaps within 1e-9 m) and writes what they did to a JSON file.

Usage: ``rule_run.py OUT_JSON [doubled]``; ``doubled`` first replaces the rule
``core.spacing.time_headway_gap_m`` by ``doubled_headway_gap`` (twice the headway), before
anything imports the batched kernels, so both worlds must take the new rule from there.
"""

from __future__ import annotations

import dataclasses
import json
import sys


def doubled_headway_gap(speed_mps: float, standstill_m: float, headway_s: float) -> float:
    """The constant-time-headway gap (m) with twice the headway."""
    return standstill_m + 2.0 * headway_s * max(speed_mps, 0.0)


def run(steps: int = 120) -> dict[str, list[float]]:
    """Run both worlds ``steps`` ticks; the first follower's desired gap (m) and speed
    (m/s) and the last follower's x (m) at every tick, from the batched world."""
    import numpy as np

    from openconvoy.comms.loss import LossConfig
    from openconvoy.core.spacing import SpacingConfig
    from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
    from openconvoy.policies.spec import load_policy

    mc = load_policy("paper").member_config
    mc = dataclasses.replace(mc, spacing=SpacingConfig(kind="constant-time-headway"))
    loss = LossConfig(per=0.1)
    vec = VectorConvoyEnv(1, "paper", n_followers=2, member_config=mc, loss=[loss])
    env = ConvoyEnv("paper", n_followers=2, member_config=mc, loss=loss)
    agents = env.possible_agents
    policies = [load_policy("paper") for _ in agents]
    vobs, _ = vec.reset(seed=10)
    env.reset(seed=10)
    out: dict[str, list[float]] = {"desired": [], "speed": [], "x": []}
    for k in range(steps):
        actions = np.array([[p.act(vobs[0, j]) for j, p in enumerate(policies)]], np.float32)
        vobs, _, _, _, vinfo = vec.step(actions)
        _, _, _, _, info = env.step({a: actions[0, j] for j, a in enumerate(agents)})
        x, y = vec.plant.x, vec.plant.y
        assert np.abs(env.plant.x - x).max() <= 1e-9, k
        assert np.abs(env.plant.y - y).max() <= 1e-9, k
        for j, a in enumerate(agents):
            assert abs(info[a]["desired_gap_m"] - vinfo["desired_gap_m"][0, j]) <= 1e-9, k
        out["desired"].append(float(vinfo["desired_gap_m"][0, 0]))
        out["speed"].append(float(vinfo["speed_mps"][0, 0]))
        out["x"].append(float(x[-1]))
    return out


if __name__ == "__main__":
    if sys.argv[2:] == ["doubled"]:
        from openconvoy.core import spacing

        spacing.time_headway_gap_m = doubled_headway_gap
    with open(sys.argv[1], "w") as f:
        json.dump(run(), f)
