"""The leaderboard (``openconvoy experiment leaderboard``): policies × scenarios × link
conditions × seeds, written as one table with 95 % intervals, and a plot.

One TOML file describes it::

    [leaderboard]
    name = "leaderboard"
    policies = ["paper", "paper-mpc", "paper-mpc-state"]   # specs, or [policy.*] names
    scenarios = ["paper", "track", "emergency-braking", "highway-cut-in"]
    seeds = 10                                # or a list of seeds
    duration_s = 60.0                         # optional: default each scenario's

    [[loss]]                                  # one table per link condition
    name = "per"                              # a plain word: the condition's label
    model = "bernoulli"                       # or "gilbert-elliott"
    pers = [0.0, 0.2, 0.4, 0.6, 0.8]
    mean_burst_s = 1.0                        # gilbert-elliott's mean burst (s)
    latency_s = 0.0                           # delivery delay (s)

    [scenario.emergency-braking.policy]       # optional: keys every classical policy takes
    speed_limit_mps = 40.0                    # in that scenario (the presets' 5 m/s suits
                                              # the small cars, not a highway)
    [scenario.track.convoy]                   # optional: that scenario's [convoy] table
    n_followers = 2

    [policy.my-pd]                            # optional inline policies, as in per-sweep
    base = "paper"

    [executor]                                # optional, as in per-sweep
    kind = "local"

Each (scenario, condition) is one per-sweep (``experiments.sweep``: the same executors,
batching where the policy allows, per-run files) under ``cells/<scenario>/<condition>/``.
The table has one row per (scenario, condition, PER, policy): for the p95 platooning
error, the mean speed difference, the minimum gap, collisions and string stability, the
mean over seeds and its 95 % confidence interval (Student's t on the per-seed values),
plus how many runs collided. ``leaderboard.csv`` and ``leaderboard.md`` hold it,
``leaderboard.png`` plots it. A leaderboard resumes: run again on the same directory (or
``--resume DIR``) and finished cells are read, not rerun, and an interrupted cell runs
only the runs it lacks.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from openconvoy.core.config import Range, dumps_toml, from_dict, load_toml, to_dict
from openconvoy.core.errors import ConfigError
from openconvoy.experiments.executor import Executor, ExecutorConfig
from openconvoy.experiments.runs import ConvoySection, LossSection
from openconvoy.experiments.sweep import (
    RESUME_DIR,
    ExperimentConfig,
    SweepInterrupted,
    policy_dirnames,
    read_summary,
    run_dirname,
    run_experiment,
)
from openconvoy.policies.spec import PolicySpec

SCENARIOS: tuple[str, ...] = ("paper", "track", "emergency-braking", "highway-cut-in")
"""The issue's four scenarios, the default."""

KEYS: tuple[str, ...] = (
    "p95_platooning_error_m",
    "mean_speed_difference_mps",
    "min_gap_m",
    "collisions",
    "string_stability",
)
"""The metrics of the table (``metrics.json`` keys), each with its 95 % interval."""

HEADINGS: dict[str, str] = {
    "p95_platooning_error_m": "p95 error (m)",
    "mean_speed_difference_mps": "speed diff. (m/s)",
    "min_gap_m": "min gap (m)",
    "collisions": "collisions",
    "string_stability": "string stab.",
}

CONFIDENCE = 0.95


def _plain(word: str) -> bool:
    return bool(word) and all(c.isalnum() or c in "-_." for c in word)


def _dirname(text: str) -> str:
    """A directory name for a scenario spec (``track-file:a/b.json`` -> ``track-file_a_b.json``)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


@dataclass(frozen=True)
class LossCondition:
    """One link condition (a ``[[loss]]`` table): a loss model at some PERs, with a
    delivery delay; times in seconds."""

    name: str
    pers: tuple[Annotated[float, Range(0.0, 1.0)], ...]
    model: str = "bernoulli"
    mean_burst_s: Annotated[float, Range(0.0, 3600.0, lo_open=True)] = 1.0
    latency_s: Annotated[float, Range(0.0, 60.0)] = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "pers", tuple(float(p) for p in self.pers))
        if not _plain(self.name):
            raise ConfigError(f"loss name {self.name!r}: a plain word (letters, digits, - _ .)")
        if not self.pers or len(set(self.pers)) != len(self.pers):
            raise ConfigError(f"loss {self.name}: pers must be given and not repeat")
        self.section()  # the channel's own checks

    def section(self) -> LossSection:
        """This condition as a sweep's ``[loss]`` table."""
        return LossSection(
            model=self.model, mean_burst_s=self.mean_burst_s, latency_s=self.latency_s
        )


DEFAULT_LOSS: tuple[LossCondition, ...] = (
    LossCondition("per", (0.0, 0.2, 0.4, 0.6, 0.8)),
    LossCondition("bursts", (0.3, 0.6), model="gilbert-elliott", mean_burst_s=1.0),
    LossCondition("latency-100ms", (0.0, 0.3), latency_s=0.1),
)
"""The issue's conditions: PER 0-0.8, Gilbert-Elliott bursts (1 s), 100 ms latency."""


@dataclass(frozen=True)
class LeaderboardConfig:
    """A whole leaderboard (see the module docstring for its TOML form)."""

    policies: tuple[str, ...]
    name: str = "leaderboard"
    scenarios: tuple[str, ...] = SCENARIOS
    seeds: tuple[Annotated[int, Range(0, 4294967295)], ...] | Annotated[int, Range(1, 100000)] = 10
    duration_s: Annotated[float, Range(0.0, 604800.0, lo_open=True)] | None = None
    loss: tuple[LossCondition, ...] = DEFAULT_LOSS
    scenario: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per scenario: ``policy`` (keys every classical policy takes there), ``convoy``."""
    policy: dict[str, dict[str, Any]] = field(default_factory=dict)
    executor: ExecutorConfig = field(default_factory=ExecutorConfig, compare=False)

    def __post_init__(self) -> None:
        seeds = self.seeds
        object.__setattr__(
            self, "seeds", tuple(range(seeds)) if isinstance(seeds, int) else tuple(seeds)
        )
        object.__setattr__(self, "policies", tuple(self.policies))
        object.__setattr__(self, "scenarios", tuple(self.scenarios))
        object.__setattr__(self, "loss", tuple(self.loss))
        for what, items in (("policies", self.policies), ("scenarios", self.scenarios)):
            if not items or len(set(items)) != len(items):
                raise ConfigError(f"leaderboard: {what} must be given and not repeat")
        if not self.loss or len({c.name for c in self.loss}) != len(self.loss):
            raise ConfigError("leaderboard: [[loss]] names must be given and not repeat")
        for name, table in self.scenario.items():
            if name not in self.scenarios:
                raise ConfigError(f"[scenario.{name}]: not one of the leaderboard's scenarios")
            extra = set(table) - {"policy", "convoy"}
            if extra:
                raise ConfigError(f"[scenario.{name}]: unknown key(s) {', '.join(sorted(extra))}")
        for scenario in self.scenarios:  # every cell's experiment checks itself now
            for condition in self.loss:
                self.cell(scenario, condition)

    @property
    def seed_values(self) -> tuple[int, ...]:
        """The seeds as a tuple."""
        assert isinstance(self.seeds, tuple)
        return self.seeds

    def cell(self, scenario: str, condition: LossCondition) -> tuple[ExperimentConfig, dict]:
        """The per-sweep of one (scenario, condition) and its labels -> our policy labels."""
        settings = self.scenario.get(scenario, {})
        overrides = settings.get("policy", {})
        inline, labels = dict(self.policy), {}
        for label in self.policies:
            labels[_scenario_label(label, scenario, overrides, inline, self.policy)] = label
        convoy = from_dict(ConvoySection, settings.get("convoy", {}), f"scenario.{scenario}.convoy")
        experiment = ExperimentConfig(
            name=f"{self.name}-{_dirname(scenario)}-{condition.name}",
            scenario=scenario,
            policies=tuple(labels),
            pers=condition.pers,
            seeds=self.seed_values,
            duration_s=self.duration_s,
            convoy=convoy,
            loss=condition.section(),
            policy=inline,
            executor=self.executor,
        )
        return experiment, labels

    def to_toml(self) -> str:
        """The leaderboard file for this config, every value written out."""
        data = to_dict(self)
        top = {k: v for k, v in data.items() if k not in ("loss", "scenario", "policy", "executor")}
        out: dict[str, Any] = {"leaderboard": top, "loss": [to_dict(c) for c in self.loss]}
        for key in ("scenario", "policy"):
            if getattr(self, key):
                out[key] = data[key]
        return dumps_toml(out)

    @classmethod
    def from_toml(cls, path: str | Path) -> LeaderboardConfig:
        """Load a leaderboard file, strictly (unknown tables or keys are errors)."""
        data = load_toml(path)
        where = str(path)
        unknown = set(data) - {"leaderboard", "loss", "scenario", "policy", "executor"}
        if unknown:
            raise ConfigError(f"{where}: unknown table(s) {', '.join(sorted(unknown))}")
        if "leaderboard" not in data:
            raise ConfigError(f"{where}: missing the [leaderboard] table")
        table = dict(data["leaderboard"])
        if "loss" in table:
            raise ConfigError(f"{where}: loss conditions are [[loss]] tables of their own")
        for key in ("scenario", "policy", "executor"):
            if key in data:
                table[key] = data[key]
        config = from_dict(cls, table, where)
        if "loss" not in data:
            return config
        if not isinstance(data["loss"], list):
            raise ConfigError(f"{where}: loss conditions are [[loss]] tables")
        loss = tuple(
            from_dict(LossCondition, c, f"{where}: loss[{i}]") for i, c in enumerate(data["loss"])
        )
        return dataclasses.replace(config, loss=loss)


def _scenario_label(
    label: str,
    scenario: str,
    overrides: dict[str, Any],
    inline: dict[str, dict[str, Any]],
    declared: dict[str, dict[str, Any]],
) -> str:
    """``label`` as the cell's sweep runs it: with the scenario's policy ``overrides`` it
    becomes an inline policy ``<name>-<scenario>`` (added to ``inline``)."""
    if not overrides:
        return label
    spec = PolicySpec.parse(label)
    if spec.learned or spec.plugin:
        raise ConfigError(
            f"[scenario.{scenario}.policy]: {label} is not a classical policy; "
            "scenario overrides apply to presets, policy files and [policy.*] tables"
        )
    if spec.base in declared:
        table = dict(declared[spec.base])
    elif spec.toml:
        table = dict(load_toml(spec.base)["policy"])
    else:
        table = {"base": spec.base}
    name = f"{Path(spec.base).stem if spec.toml else spec.base}-{_dirname(scenario)}"
    table.pop("name", None)
    inline[name] = {**table, **overrides}
    return str(spec.with_base(name))


# --- running -----------------------------------------------------------------------------


class LeaderboardInterrupted(SweepInterrupted):
    """Ctrl-C or SIGTERM stopped a leaderboard: finished runs and cells are kept."""

    def __init__(self, out: Path) -> None:
        self.out = out
        Exception.__init__(
            self,
            f"interrupted: the finished runs are kept in {out}; "
            f"openconvoy experiment leaderboard --resume {out} runs the rest",
        )


def same_cells(stored: LeaderboardConfig, config: LeaderboardConfig) -> bool:
    """Whether ``config`` may run in the directory of ``stored``: the same leaderboard,
    perhaps on other scenarios (``--scenarios``), so the cells they share are the same."""
    if dataclasses.replace(stored, scenarios=config.scenarios, scenario={}) != (
        dataclasses.replace(config, scenario={})
    ):
        return False
    shared = set(stored.scenarios) & set(config.scenarios)
    return all(stored.scenario.get(s) == config.scenario.get(s) for s in shared)


def run_leaderboard(
    config: LeaderboardConfig,
    out_dir: str | Path,
    progress: bool = True,
    figures: bool = True,
    executor: ExecutorConfig | Executor | None = None,
    run_logs: bool = True,
    say: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Run (or finish) every cell of ``config`` in ``out_dir`` and write the table and
    plot; the table's rows. A directory that holds another leaderboard is refused."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    copy = out / "leaderboard.toml"
    text = config.to_toml()
    if copy.is_file() and not same_cells(LeaderboardConfig.from_toml(copy), config):
        raise ConfigError(f"{out} holds another leaderboard (its leaderboard.toml differs)")
    copy.write_text(text, encoding="utf-8")
    rows: list[dict[str, Any]] = []
    for scenario in config.scenarios:
        for condition in config.loss:
            cell_dir = out / "cells" / _dirname(scenario) / condition.name
            rows += _run_cell(
                config, scenario, condition, cell_dir, progress, executor, run_logs, say
            )
    write_table(out, rows)
    if figures:
        from openconvoy.experiments.figures import leaderboard_figure

        leaderboard_figure(rows, out / "leaderboard.png")
    return rows


def _run_cell(
    config: LeaderboardConfig,
    scenario: str,
    condition: LossCondition,
    cell_dir: Path,
    progress: bool,
    executor: ExecutorConfig | Executor | None,
    run_logs: bool,
    say: Callable[[str], None] | None,
) -> list[dict[str, Any]]:
    """One cell's sweep (skipped when complete, resumed when interrupted) and its rows."""
    experiment, labels = config.cell(scenario, condition)
    complete = (cell_dir / "summary.json").is_file() and not (cell_dir / RESUME_DIR).exists()
    if not complete:
        resume = (cell_dir / RESUME_DIR).is_dir() and (cell_dir / "experiment.toml").is_file()
        try:
            run_experiment(
                experiment,
                cell_dir,
                progress=progress,
                figures=False,
                executor=executor,
                run_logs=run_logs,
                say=say,
                resume=resume,
            )
        except SweepInterrupted:
            raise LeaderboardInterrupted(cell_dir.parent.parent.parent) from None
    read_summary(cell_dir)  # a cell that finished says so; its runs give the intervals
    return cell_rows(experiment, labels, cell_dir, scenario, condition.name)


def cell_rows(
    experiment: ExperimentConfig,
    labels: dict[str, str],
    cell_dir: Path,
    scenario: str,
    loss: str,
) -> list[dict[str, Any]]:
    """The table's rows of one finished cell, from its runs' ``metrics.json``."""
    names = policy_dirnames(experiment.policies)
    runs: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for label, rc in experiment.run_configs():
        path = cell_dir / run_dirname(label, rc, names[label]) / "metrics.json"
        runs.setdefault((label, rc.per), []).append(json.loads(path.read_text(encoding="utf-8")))
    rows = []
    order = sorted(
        runs, key=lambda k: (experiment.pers.index(k[1]), experiment.policies.index(k[0]))
    )
    for label, per in order:
        metrics = runs[(label, per)]
        row: dict[str, Any] = {
            "scenario": scenario,
            "loss": loss,
            "per": per,
            "policy": labels[label],
            "runs": len(metrics),
            "runs_with_collision": sum(1 for m in metrics if (m.get("collisions") or 0) > 0),
        }
        for key in KEYS:
            row[key] = interval([_number(m.get(key)) for m in metrics])
        rows.append(row)
    return rows


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def interval(values: Sequence[float], confidence: float = CONFIDENCE) -> dict[str, float]:
    """The mean of the finite ``values`` and its two-sided ``confidence`` interval
    (Student's t, sample standard deviation): ``{"mean", "lo", "hi", "n"}``; the interval
    is NaN with fewer than two values (and the mean with none)."""
    from scipy import stats as st

    v = np.array([x for x in values if math.isfinite(x)], dtype=float)
    n = len(v)
    if n == 0:
        return {"mean": math.nan, "lo": math.nan, "hi": math.nan, "n": 0}
    mean = float(v.mean())
    if n < 2:
        return {"mean": mean, "lo": math.nan, "hi": math.nan, "n": 1}
    half = float(st.t.ppf(0.5 + confidence / 2, n - 1) * v.std(ddof=1) / math.sqrt(n))
    return {"mean": mean, "lo": mean - half, "hi": mean + half, "n": n}


# --- the table ---------------------------------------------------------------------------


def _fmt(v: float) -> str:
    return "" if not math.isfinite(v) else format(v, ".6g")


def table_csv(rows: Sequence[dict[str, Any]]) -> str:
    """The table as CSV: scenario, loss, per, policy, runs, runs_with_collision, then
    ``<metric>_mean``, ``_lo``, ``_hi`` (the 95 % interval), ``_n`` (finite values)."""
    header = ["scenario", "loss", "per", "policy", "runs", "runs_with_collision"]
    header += [f"{k}_{s}" for k in KEYS for s in ("mean", "lo", "hi", "n")]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(
            [r["scenario"], r["loss"], _fmt(r["per"]), r["policy"], r["runs"]]
            + [r["runs_with_collision"]]
            + [
                _fmt(r[k][s]) if s != "n" else str(r[k]["n"])
                for k in KEYS
                for s in ("mean", "lo", "hi", "n")
            ]
        )
    return buf.getvalue()


def _cell_md(stat: dict[str, float]) -> str:
    if not math.isfinite(stat["mean"]):
        return "–"
    if not math.isfinite(stat["lo"]):
        return f"{stat['mean']:.3g}"
    return f"{stat['mean']:.3g} [{stat['lo']:.3g}, {stat['hi']:.3g}]"


def table_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The table as Markdown: each metric ``mean [lo, hi]`` (95 % interval over seeds)."""
    head = ["scenario", "loss", "PER", "policy", "runs"] + [HEADINGS[k] for k in KEYS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["scenario"], r["loss"], f"{r['per']:g}", f"`{r['policy']}`", str(r["runs"])]
        cells += [_cell_md(r[k]) for k in KEYS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_table(out: Path, rows: Sequence[dict[str, Any]]) -> None:
    """``leaderboard.csv``, ``leaderboard.md`` and ``leaderboard.json`` in ``out``."""
    from openconvoy.core import metrics as mt

    (out / "leaderboard.csv").write_text(table_csv(rows), encoding="utf-8")
    (out / "leaderboard.md").write_text(table_markdown(rows), encoding="utf-8")
    text = json.dumps(mt.json_safe({"rows": list(rows)}), indent=2) + "\n"
    (out / "leaderboard.json").write_text(text, encoding="utf-8")


def with_overrides(config: LeaderboardConfig, **changes: Any) -> LeaderboardConfig:
    """``config`` with top-level fields changed (re-validated); with other ``scenarios``,
    the ``[scenario.*]`` settings of those left out are dropped."""
    if "scenarios" in changes:
        kept = {k: v for k, v in config.scenario.items() if k in changes["scenarios"]}
        changes = {"scenario": kept, **changes}
    return dataclasses.replace(config, **changes)
