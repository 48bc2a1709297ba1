"""Validation of a trained policy file: deterministic simulated runs, one objective.

The same runs ``openconvoy sim --policy FILE`` makes (the experiments' ``run_sim``) on the
``paper`` scenario for every (PER, seed) of a grid, scored with the tuning objective
(``openconvoy.train.tune.objective_of``: mean p95 platooning error in metres, plus 100 m
per collision per run, plus the mean speed difference). Training validates every
checkpoint this way and keeps the best, as SB3's EvalCallback keeps a best model; the
seeds are kept apart from those reports use, so the selection does not see the test runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openconvoy.train.tune import TuneConfig, objective_of


@dataclass(frozen=True)
class Validation:
    """A policy file's validation: the objective (lower is better) and the runs' metrics."""

    path: str
    steps: int
    objective: float
    metrics: tuple[dict[str, Any], ...]

    def to_json(self) -> dict[str, Any]:
        keys = ("p95_platooning_error_m", "mean_speed_difference_mps", "collisions")
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
) -> Validation:
    """Run ``policy`` (any spec) on the grid (runs of ``duration_s``, default the
    scenario's) and score it; ``steps`` is recorded with the result."""
    from openconvoy.experiments.runs import RunConfig, run_sim

    metrics = tuple(
        run_sim(
            RunConfig(
                scenario=scenario, policy=str(policy), per=per, seed=seed, duration_s=duration_s
            )
        ).metrics
        for per in pers
        for seed in seeds
    )
    return Validation(str(policy), int(steps), objective_of(metrics, TuneConfig()), metrics)
