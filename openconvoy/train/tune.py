"""``openconvoy tune``: Optuna search over a classical policy's parameters.

Each trial is a ClassicalConfig (the base policy with some parameters changed), written
as a policy TOML file and run with the experiments' ``run_sim`` on every (PER, seed) of
the evaluation grid, exactly as ``openconvoy sim --policy FILE`` would run it. The
objective, to minimize, is

    mean over runs of p95_platooning_error_m  +  collision_penalty_m * collisions per run
    + speed_difference_weight * mean over runs of mean_speed_difference_mps

so a collision outweighs any spacing gain. The best trial is written as a TOML policy
file (``classical_to_toml``) that ``--policy`` accepts.

Parameters (``PARAMETERS``; names are dotted ClassicalConfig paths): the speed
controller's gains (``speed.kp``, ``speed.kd``, ``speed.ki`` for ``pid``), the heading
controller's gain (``heading.gain`` for Stanley, ``heading.lookahead_s`` for pure
pursuit) and the spacing policy's shape (``member.spacing.headway_s``,
``member.spacing.standstill_m`` for time-headway policies). A constant-distance policy's
``distance_m`` is the specification, not a tunable: it is left alone.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from openconvoy.core.errors import ConfigError
from openconvoy.policies.classical import ClassicalConfig
from openconvoy.policies.spec import classical_config, classical_to_toml


@dataclass(frozen=True)
class Param:
    """A searched parameter: dotted path in ClassicalConfig, range, log scale."""

    path: str
    low: float
    high: float
    log: bool = False


PARAMETERS: dict[str, Param] = {
    p.path: p
    for p in (
        Param("speed.kp", 0.05, 5.0, log=True),
        Param("speed.kd", 0.1, 5.0, log=True),
        Param("speed.ki", 0.0, 0.5),
        Param("heading.gain", 0.05, 2.0, log=True),
        Param("heading.lookahead_s", 0.5, 2.0),
        Param("member.spacing.headway_s", 0.3, 2.0),
        Param("member.spacing.standstill_m", 1.0, 5.0),
    )
}


def applicable(config: ClassicalConfig) -> list[str]:
    """The parameters that mean something for ``config``'s controllers and spacing."""
    out = ["speed.kp", "speed.kd"]
    if config.speed.kind == "pid":
        out.append("speed.ki")
    out.append("heading.gain" if config.heading.kind == "stanley" else "heading.lookahead_s")
    if config.member.spacing.kind != "constant-distance":
        out += ["member.spacing.headway_s", "member.spacing.standstill_m"]
    return out


def with_values(config: ClassicalConfig, values: dict[str, float], name: str) -> ClassicalConfig:
    """``config`` with dotted-path ``values`` replaced, renamed ``name``."""
    out = dataclasses.replace(config, name=name)
    for path, value in values.items():
        out = _replace_path(out, path.split("."), value)
    return out


def _replace_path(obj: Any, parts: list[str], value: float) -> Any:
    if not dataclasses.is_dataclass(obj) or parts[0] not in {f.name for f in dataclasses.fields(obj)}:
        raise ConfigError(f"unknown parameter path component {parts[0]!r}")
    if len(parts) == 1:
        return dataclasses.replace(obj, **{parts[0]: float(value)})
    return dataclasses.replace(obj, **{parts[0]: _replace_path(getattr(obj, parts[0]), parts[1:], value)})


@dataclass(frozen=True)
class TuneConfig:
    """A tuning study.

    Attributes:
        base: classical policy spec to start from (preset or TOML).
        trials: Optuna trials.
        pers: packet error rates of the evaluation grid.
        seeds: seeds of the evaluation grid (every PER runs every seed); apart from the
            seeds reports use (0..), so a tuned policy is not scored on its own training runs.
        scenario: scenario spec the runs use.
        duration_s: run length (None: the scenario's).
        params: parameters to search (default: ``applicable(base)``).
        collision_penalty_m: objective cost of one collision, metres of p95 error.
        speed_difference_weight: objective weight of the mean speed difference (s).
        seed: the sampler's seed (the same seed gives the same study).
        name: name of the written policy.
    """

    base: str = "paper"
    trials: int = 30
    pers: tuple[float, ...] = (0.0, 0.3, 0.6)
    seeds: tuple[int, ...] = (1000, 1001)
    scenario: str = "paper"
    duration_s: float | None = None
    params: tuple[str, ...] = ()
    collision_penalty_m: float = 100.0
    speed_difference_weight: float = 1.0
    seed: int = 0
    name: str = "tuned"

    def __post_init__(self) -> None:
        for name in ("pers", "seeds", "params"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.trials < 1 or not self.pers or not self.seeds:
            raise ConfigError("tune needs at least one trial, one PER and one seed")
        unknown = [p for p in self.params if p not in PARAMETERS]
        if unknown:
            raise ConfigError(f"unknown tuning parameter(s) {', '.join(unknown)}; expected some of {', '.join(PARAMETERS)}")


@dataclass
class TuneResult:
    """The best configuration, its objective and the per-trial history."""

    best: ClassicalConfig
    best_value: float
    best_params: dict[str, float]
    base_value: float
    history: list[dict[str, Any]] = field(default_factory=list)


Evaluate = Callable[[ClassicalConfig], float]


def objective_of(metrics: Sequence[dict[str, Any]], config: TuneConfig) -> float:
    """The objective (lower is better) of a grid's metrics (``metrics.json`` dicts)."""
    p95 = [m["p95_platooning_error_m"] for m in metrics]
    p95 = [v if v is not None and math.isfinite(v) else 1e3 for v in p95]
    collisions = sum(int(m["collisions"] or 0) for m in metrics)
    speed = [m["mean_speed_difference_mps"] for m in metrics]
    speed = [v if v is not None and math.isfinite(v) else 10.0 for v in speed]
    return float(
        np.mean(p95)
        + config.collision_penalty_m * collisions / len(metrics)
        + config.speed_difference_weight * np.mean(speed)
    )


def grid_evaluator(config: TuneConfig, workdir: Path) -> Evaluate:
    """Evaluate a candidate with ``run_sim`` over ``config``'s PER x seed grid."""
    from openconvoy.experiments.runs import RunConfig, run_sim

    counter = iter(range(1_000_000))

    def evaluate(candidate: ClassicalConfig) -> float:
        path = workdir / f"trial_{next(counter)}.toml"
        path.write_text(classical_to_toml(candidate), encoding="utf-8")
        metrics = [
            run_sim(RunConfig(
                scenario=config.scenario, policy=str(path), per=per, seed=seed,
                duration_s=config.duration_s,
            )).metrics
            for per in config.pers
            for seed in config.seeds
        ]
        return objective_of(metrics, config)

    return evaluate


def tune(config: TuneConfig, evaluate: Evaluate | None = None, progress_bar: bool = False) -> TuneResult:
    """Run the study; ``evaluate`` defaults to ``grid_evaluator`` (simulated runs)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    base = classical_config(config.base)
    params = list(config.params) or applicable(base)
    with tempfile.TemporaryDirectory(prefix="openconvoy-tune-") as tmp:
        ev = evaluate or grid_evaluator(config, Path(tmp))
        base_value = ev(dataclasses.replace(base, name=config.name))
        history: list[dict[str, Any]] = []

        def objective(trial: optuna.Trial) -> float:
            values = {
                p: trial.suggest_float(p, PARAMETERS[p].low, PARAMETERS[p].high, log=PARAMETERS[p].log)
                for p in params
            }
            value = ev(with_values(base, values, config.name))
            history.append({"trial": trial.number, "value": value, **values})
            return value

        sampler = optuna.samplers.TPESampler(seed=config.seed)
        study = optuna.create_study(direction="minimize", sampler=sampler)
        # The base's own values first: the study can only improve on the starting point.
        study.enqueue_trial({p: _get_path(base, p) for p in params if _in_range(base, p)})
        study.optimize(objective, n_trials=config.trials, show_progress_bar=progress_bar)
    best_params = {k: float(v) for k, v in study.best_params.items()}
    described = ", ".join(f"{k} {v:.4g}" for k, v in best_params.items())
    best = dataclasses.replace(
        with_values(base, best_params, config.name),
        description=f"{config.base} tuned by openconvoy tune ({config.trials} trials, PER "
        f"{', '.join(f'{p:g}' for p in config.pers)}, {len(config.seeds)} seeds): {described}",
    )
    return TuneResult(best, float(study.best_value), best_params, base_value, history)


def _get_path(config: ClassicalConfig, path: str) -> float:
    obj: Any = config
    for part in path.split("."):
        obj = getattr(obj, part)
    return float(obj)


def _in_range(config: ClassicalConfig, path: str) -> bool:
    p = PARAMETERS[path]
    return p.low <= _get_path(config, path) <= p.high


def write_tuned(result: TuneResult, out: str | Path) -> Path:
    """Write the best policy as TOML (``--policy`` accepts it) and ``<out>.json`` with
    the study's numbers next to it."""
    out = Path(out)
    if out.suffix != ".toml":
        raise ConfigError(f"{out}: the tuned policy is a .toml file")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(classical_to_toml(result.best), encoding="utf-8")
    summary = {
        "best_value": result.best_value,
        "base_value": result.base_value,
        "best_params": result.best_params,
        "trials": result.history,
    }
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    return out
