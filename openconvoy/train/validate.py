"""Validation of a trained policy file: deterministic simulated runs, one objective.

The same runs ``openconvoy sim --policy FILE`` makes (the experiments' ``run_sim``) on the
``paper`` scenario for every (PER, seed) of a grid, scored with the tuning objective
(``openconvoy.train.tune.objective_of``: mean p95 platooning error in metres, plus 100 m
per collision per run, plus the mean speed difference) plus the mean p95 distance of the
followers from the scenario's path (``PATH_KEY``). Training validates every
checkpoint this way and keeps the best, as SB3's EvalCallback keeps a best model; the
seeds are kept apart from those reports use, so the selection does not see the test runs.

All runs of the grid step together in one ``VectorConvoyEnv`` (convoy ``b`` is run ``b``:
the same seed, PER and start as ``run_sim``'s, bit-equal states), the policy acting through
``act_batch`` (one forward pass per tick for a learned policy); the metrics come from the
same ``core.metrics`` functions on the same rows a run's log holds. A policy without
``act_batch`` or a scenario the batched simulator refuses runs run by run (``run_sim``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openconvoy.core import metrics as mt
from openconvoy.core.errors import ConfigError, DependencyMissing
from openconvoy.core.policy import BatchPolicy
from openconvoy.train.tune import TuneConfig, objective_of

KEYS = ("p95_platooning_error_m", "mean_speed_difference_mps", "collisions", "min_gap_m")
"""The metrics a validation keeps per run (with ``PATH_KEY``)."""
PATH_KEY = "p95_path_error_m"
"""The 95th percentile over followers and ticks of the distance (m) from the scenario's
path. The platooning error is a straight-line gap, blind to a follower beside its
predecessor; a validation scores this too (added to the objective), so a policy that
keeps its gap while leaving the road is not the one kept."""


@dataclass(frozen=True)
class Validation:
    """A policy file's validation: the objective (lower is better) and the runs' metrics."""

    path: str
    steps: int
    objective: float
    metrics: tuple[dict[str, Any], ...]

    def to_json(self) -> dict[str, Any]:
        keys = ("p95_platooning_error_m", "mean_speed_difference_mps", "collisions", PATH_KEY)
        return {
            "path": self.path,
            "steps": self.steps,
            "objective": self.objective,
            "runs": [{k: m.get(k) for k in keys} for m in self.metrics],
        }


def validate(
    policy: str | Path,
    pers: Sequence[float],
    seeds: Sequence[int],
    steps: int = 0,
    scenario: str = "paper",
    duration_s: float | None = None,
    batched: bool = True,
) -> Validation:
    """Run ``policy`` (any spec) on the grid (runs of ``duration_s``, default the
    scenario's) and score it; ``steps`` is recorded with the result. ``batched=False``
    runs ``run_sim`` run by run (the reference the batched path is tested against)."""
    runs = [(float(per), int(seed)) for per in pers for seed in seeds]
    metrics = batched_metrics(str(policy), runs, scenario, duration_s) if batched else None
    if metrics is None:
        metrics = [_run_metrics(str(policy), per, seed, scenario, duration_s) for per, seed in runs]
    return Validation(str(policy), int(steps), validation_objective(metrics), tuple(metrics))


def comparison_lines(chosen: Validation, base: Validation) -> list[str]:
    """The validation table of a trained policy beside its reference on the same grid
    (means over the grid's runs), then a warning line when the policy scores worse."""
    rows = [("objective (lower is better)", chosen.objective, base.objective)]
    for key, name in (
        ("p95_platooning_error_m", "p95 platooning error (m)"),
        ("mean_speed_difference_mps", "mean speed difference (m/s)"),
        ("min_gap_m", "min gap (m)"),
        ("collisions", "collisions (total)"),
        (PATH_KEY, "p95 distance from path (m)"),
    ):
        total = key == "collisions"
        rows.append((name, _grid(chosen.metrics, key, total), _grid(base.metrics, key, total)))
    label = f"base {Path(base.path).name}"
    n = len(chosen.metrics)
    lines = [f"validation ({n} run{'s' * (n != 1)})   {'trained':>12}{label:>16}"]
    lines += [f"  {name:<30}{a:>12.4g}{b:>16.4g}" for name, a, b in rows]
    if chosen.objective > base.objective:
        lines.append(
            f"warning: the trained policy validates worse than {Path(base.path).name} "
            f"(objective {chosen.objective:.4g} against {base.objective:.4g}): train longer, "
            "or deploy the base"
        )
    return lines


def _grid(metrics: Sequence[dict[str, Any]], key: str, total: bool) -> float:
    """The mean (or, with ``total``, the sum) of ``key`` over the runs, NaN when none."""
    values = [float(m[key]) for m in metrics if m.get(key) is not None]
    finite = [v for v in values if np.isfinite(v)]
    if not finite:
        return float("nan")
    return float(np.sum(finite) if total else np.mean(finite))


def validation_objective(metrics: Sequence[dict[str, Any]]) -> float:
    """The tuning objective (``objective_of``) plus the mean ``PATH_KEY`` (m; 0 for a
    scenario without a path)."""
    path = [m.get(PATH_KEY) for m in metrics]
    finite = [float(v) if v is not None and np.isfinite(v) else 0.0 for v in path]
    return objective_of(metrics, TuneConfig()) + float(np.mean(finite))


def path_error_p95(log: dict[str, np.ndarray], scenario: Any) -> float:
    """``PATH_KEY`` of a run's log rows (``x_m``, ``y_m``, ``vehicle_id``; the leader is
    vehicle 0) on ``scenario``'s path (sampled every 0.25 m; NaN without one)."""
    path = getattr(scenario, "path", None)
    if path is None:
        return float("nan")
    points = path.sample(0.25)
    follower = log["vehicle_id"] != 0
    xy = np.stack([log["x_m"][follower], log["y_m"][follower]], axis=1)
    nearest = np.empty(len(xy))
    for i in range(0, len(xy), 512):  # bounded memory: 512 rows x path points at a time
        d = xy[i : i + 512, None, :] - points[None, :, :]
        nearest[i : i + 512] = np.sqrt((d * d).sum(axis=2).min(axis=1))
    return float(np.percentile(nearest, 95)) if len(nearest) else float("nan")


def _run_metrics(
    policy: str, per: float, seed: int, scenario: str, duration_s: float | None
) -> dict[str, Any]:
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.experiments.runs import RunConfig, run_sim

    run = run_sim(
        RunConfig(scenario=scenario, policy=policy, per=per, seed=seed, duration_s=duration_s)
    )
    out = {k: run.metrics[k] for k in KEYS}
    out[PATH_KEY] = path_error_p95(run.log, make_scenario(scenario))
    return out


def batched_metrics(
    policy: str, runs: Sequence[tuple[float, int]], scenario: str, duration_s: float | None
) -> list[dict[str, Any]] | None:
    """The metrics of ``run_sim`` for every (PER, seed) in ``runs``, from one batched
    run; None when the policy or the scenario cannot run batched."""
    from openconvoy.comms.loss import LossConfig
    from openconvoy.envs.scenarios import PathScenario, make_scenario
    from openconvoy.policies import load_policy

    p = load_policy(policy)
    if not isinstance(p, BatchPolicy):
        return None
    scene = make_scenario(scenario)
    if not isinstance(scene, PathScenario):
        return None
    if p.member_config is not None:  # run_sim starts the vehicles at the policy's gaps
        scene = scene.with_changes(spacing=p.member_config.spacing)
    try:
        from openconvoy.envs import VectorConvoyEnv  # needs numba (the batched extra)

        env = VectorConvoyEnv(
            len(runs),
            scene,
            member_config=p.member_config,
            loss=[LossConfig(per=per) for per, _ in runs],
            control_rate_hz=float(p.control_rate_hz),
            max_time_s=duration_s,
            autoreset=False,
        )
    except (ConfigError, DependencyMissing):
        return None
    p.reset()
    ticks = _rollout(env, p, [seed for _, seed in runs])
    lengths = {i: float(v) for i, v in enumerate(env.lengths)}
    return [_convoy_metrics(ticks, b, lengths, scene) for b in range(len(runs))]


def _rollout(env: Any, policy: Any, seeds: list[int]) -> dict[str, np.ndarray]:
    """Every convoy's state at every tick until its run ends (a run's log rows):
    ``x, y, speed`` (T, B, N), ``gap, desired`` (T, B, N-1), ``ticks`` (B,) rows kept."""
    obs, info = env.reset(seed=seeds)
    B = env.num_envs
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("x", "y", "speed", "gap", "desired")}

    def record(info: dict[str, Any]) -> None:
        x, y, speed = env.own_truth[0], env.own_truth[1], env.own_truth[2]
        for key, value in (
            ("x", x),
            ("y", y),
            ("speed", speed),
            ("gap", info["gap_m"]),
            ("desired", info["desired_gap_m"]),
        ):
            rows[key].append(np.array(value, dtype=float))

    record(info)
    ticks = np.ones(B, dtype=np.int64)
    alive = np.ones(B, dtype=bool)
    for _ in range(env.max_steps):
        obs, _, term, trunc, info = env.step(policy.act_batch(obs))
        record(info)
        ticks += alive
        alive &= ~(term | trunc)
        if not alive.any():
            break
    out = {k: np.stack(v) for k, v in rows.items()}
    out["ticks"] = ticks
    out["t"] = np.arange(len(rows["x"])) * env.dt
    return out


def _convoy_metrics(
    ticks: dict[str, np.ndarray], b: int, lengths: dict[int, float], scene: Any
) -> dict:
    """``core.metrics`` on convoy ``b``'s rows, as ``run_sim`` computes them from its log."""
    T = int(ticks["ticks"][b])
    N = ticks["x"].shape[2]
    nan = np.full((T, 1), np.nan)
    log = {
        "t_s": np.repeat(ticks["t"][:T], N),
        "vehicle_id": np.tile(np.arange(N), T),
        "x_m": ticks["x"][:T, b].ravel(),
        "y_m": ticks["y"][:T, b].ravel(),
        "speed_mps": ticks["speed"][:T, b].ravel(),
        "gap_m": np.hstack([nan, ticks["gap"][:T, b]]).ravel(),
        "desired_gap_m": np.hstack([nan, ticks["desired"][:T, b]]).ravel(),
        "msgs_received": np.full(T * N, -1),
        "msgs_lost": np.full(T * N, -1),
    }
    m = mt.compute_metrics(log, lengths)
    out = {k: m[k] for k in KEYS}
    out[PATH_KEY] = path_error_p95(log, scene)
    return out
