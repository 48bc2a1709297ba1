"""The fault matrix's runs as tasks for the local process pool (``test_fault_matrix.py``),
in a module of their own so the spawned workers import only what a run needs (the test
module is imported by pytest, with its collection of every preset, in the driver only).

Each task returns the smallest bumper gap (m) of any pair of convoy vehicles, every tick,
of each of its runs: the driver counts the runs and names the collisions.
"""

from __future__ import annotations

import math

import numpy as np

from openconvoy.experiments.runs import RunConfig


def worst_pairs(x: np.ndarray, y: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Per run (B,): the smallest bumper gap (m) of any pair over ``x``, ``y`` (T, B, N)
    positions (m) and the vehicles' ``lengths`` (N,, m); NaN ticks (a run that ended)
    are skipped."""
    n = x.shape[2]
    worst = np.full(x.shape[1], np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            d = np.hypot(x[:, :, i] - x[:, :, j], y[:, :, i] - y[:, :, j])
            d = d - 0.5 * (lengths[i] + lengths[j])
            worst = np.minimum(worst, np.nanmin(d, axis=0))
    return worst


def batch_worst(configs: list[RunConfig]) -> list[float]:
    """Task: ``configs`` (differing only in PER and seed) as one batched run
    (``experiments.batched.run.simulate``); each run's smallest bumper gap (m)."""
    from openconvoy.experiments.batched.run import simulate

    rec, _, env = simulate(configs)
    lengths = np.array([v.length_m for v in env.presets])
    return [float(w) for w in worst_pairs(rec.f["x_m"], rec.f["y_m"], lengths)]


def run_worst(config: RunConfig) -> float:
    """One ``ConvoyEnv`` run of ``config`` (as ``run_sim`` steps it, without its log):
    the smallest bumper gap (m) of any pair of convoy vehicles, every tick."""
    from openconvoy.experiments.runs import build_env

    env, policies = build_env(config)
    obs, _ = env.reset(seed=config.seed)
    for p in policies.values():
        p.reset(config.seed)
    lengths = [p.length_m for p in env.presets]
    n = len(lengths)
    worst = math.inf
    while env.agents:
        obs, *_ = env.step({a: policies[a].act(obs[a]) for a in env.agents})
        x, y = env.plant.x, env.plant.y
        for i in range(n):
            for j in range(i + 1, n):
                d = math.hypot(x[i] - x[j], y[i] - y[j]) - 0.5 * (lengths[i] + lengths[j])
                worst = min(worst, d)
    return worst


def runs_worst(configs: list[RunConfig]) -> list[float]:
    """Task: each of ``configs`` as its own ``ConvoyEnv`` run (``run_worst``), in order
    (several ~0.1 s runs a task, so the pool's per-task cost stays small)."""
    return [run_worst(c) for c in configs]
