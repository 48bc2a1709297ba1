"""Experiment files and the packet-error-rate sweep (``openconvoy experiment per-sweep``).

One TOML file fully describes an experiment::

    [experiment]
    name = "paper-per-sweep"
    kind = "per-sweep"
    scenario = "paper"
    policies = ["paper", "paper+ladder"]     # specs; names of [policy.*] tables too
    pers = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    seeds = [0, 1, 2]
    duration_s = 60.0                        # optional: default the scenario's
    faults = ["halt:1@30"]                   # optional: KIND:VEHICLE@T_S, in every run
    auth = "required"                        # optional: or "off" (forge faults get through)

    [convoy]                                 # optional
    vehicles = ["1/10", "1/6", "1/10"]       # presets or preset files, leader first
    n_followers = 2
    ranging = false                          # followers carry a ranging sensor
    ranging_max_range_m = 20.0               # its range (m)
    gps_noise_m = 0.0

    [loss]                                   # optional
    model = "bernoulli"                      # or "gilbert-elliott"
    mean_burst_s = 1.0
    latency_s = 0.0
    jitter_s = 0.0

    [policy.cacc-highway]                    # optional inline policy files
    base = "cacc-allpred"                    # a preset; the keys below override it
    speed_limit_mps = 40.0

    [executor]                               # optional: where the runs execute
    kind = "ray"                             # default "local" (processes on this machine)
    address = "10.0.0.5:6379"                # see openconvoy.experiments.executor
    batched = false                          # default: batched where exact (see below)

An inline ``[policy.NAME]`` table is a policy file's ``[policy]`` table; ``policies`` may
name it (with ``+ladder`` too); policy files named in ``policies`` are inlined the same way
under their file's stem. ``faults`` (``openconvoy.core.faults``: ``halt``, ``silent``,
``dead``, ``forge``) and ``security.auth`` are every run's, as ``openconvoy sim --fault/--auth``
takes them: a robustness study sweeps PERs × seeds under, say, a braking predecessor
(``halt:1@30``) or a forged leader with authentication off (``forge:0@10``, ``auth =
"off"``). The run directory keeps ``experiment.toml`` (the complete
resolved experiment, every default written out, policy files inlined), ``manifest.json`` (package version), the
inline policies as files, ``summary.json`` (DESIGN.md's shape, one row per policy and PER),
``summary.csv``, every run's ``log.csv`` and ``metrics.json`` under
``runs/<policy>/per_<PER>/seed_<seed>/``, and the figures. Rerunning from the copy gives a
byte-identical ``summary.csv``: every run is seeded, results are ordered by (policy, PER,
seed) whatever order the processes finish in, and numbers are written with fixed format.
The executor does not change a number: each run is a task that ships its log and metrics
back as bytes, and only this process writes the run directory. Nor does batching: a
policy's runs are a few tasks of one ``VectorConvoyEnv`` each (``batched.tasks``) where
the batched env takes them and the policy's ``act_batch`` is its ``act`` to the bit
(classical policies), and those tasks return the very files the per-run tasks would. A run that fails leaves
the others written, ``failures.json`` naming it, and a summary of the runs that finished.

A sweep survives interruption: each run's files are written as soon as its task ends, with
a record of its metrics and figure series under ``.resume/``; Ctrl-C (or SIGTERM) keeps
every finished run, writes no summary and says how to go on: ``experiment per-sweep
--resume DIR`` runs only the missing runs (and any that failed) and writes the summary,
byte-identical to an uninterrupted sweep's. ``.resume/`` goes once the sweep is complete.
The summary files are written whole or not at all (signals wait until both are written).
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import os
import pickle
import shutil
import signal
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from openconvoy.core import metrics as mt
from openconvoy.core.config import Range, dumps_toml, from_dict, load_toml, to_dict
from openconvoy.core.errors import ConfigError, OpenConvoyError
from openconvoy.core.faults import (
    check_auth,
    check_fault_times,
    check_faults,
    fault_specs,
    parse_fault,
)
from openconvoy.experiments.batched import tasks as batched_sweep
from openconvoy.experiments.executor import (
    Executor,
    ExecutorConfig,
    TaskFailure,
    TasksFailed,
    make_executor,
)
from openconvoy.experiments.executor import available_cores as available_cores  # re-export
from openconvoy.experiments.runs import ConvoySection, LossSection, RunConfig, write_json
from openconvoy.policies.spec import LADDER_SUFFIX as LADDER_SUFFIX  # re-export
from openconvoy.policies.spec import PolicySpec

DEFAULT_PERS: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
STATS = ("mean", "std", "min", "max")


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole experiment (see the module docstring for its TOML form)."""

    name: str = "per-sweep"
    kind: str = "per-sweep"
    scenario: str = "paper"
    policies: tuple[str, ...] = ("paper",)
    pers: tuple[Annotated[float, Range(0.0, 1.0)], ...] = DEFAULT_PERS
    seeds: tuple[Annotated[int, Range(0, 4294967295)], ...] | Annotated[int, Range(1, 100000)] = (
        0,
        1,
        2,
    )
    duration_s: Annotated[float, Range(0.0, 604800.0, lo_open=True)] | None = None
    faults: tuple[str, ...] = ()
    """Injected faults of every run, ``KIND:VEHICLE@T_S`` (``core.faults``)."""
    auth: str = "required"
    """``"required"`` (members reject forged messages) or ``"off"``."""
    convoy: ConvoySection = field(default_factory=ConvoySection)
    loss: LossSection = field(default_factory=LossSection)
    policy: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Inline policy tables by name (each a policy file's ``[policy]`` table)."""
    executor: ExecutorConfig = field(default_factory=ExecutorConfig, compare=False)
    """Where the runs execute (``[executor]``): not part of the experiment's results, so
    neither compared nor written to the run directory's copy (which reruns locally)."""

    def __post_init__(self) -> None:
        if self.kind != "per-sweep":
            raise ConfigError(f"unknown experiment kind {self.kind!r}; expected 'per-sweep'")
        object.__setattr__(self, "policies", tuple(self.policies))
        object.__setattr__(self, "pers", tuple(float(p) for p in self.pers))
        seeds = self.seeds
        if isinstance(seeds, int):  # ``seeds = 3`` means seeds 0, 1, 2
            seeds = tuple(range(seeds))
        object.__setattr__(self, "seeds", tuple(int(s) for s in seeds))
        seeds = self.seed_values
        if not self.policies:
            raise ConfigError("an experiment needs at least one policy")
        if len(set(self.policies)) != len(self.policies):
            raise ConfigError(f"policies repeat: {', '.join(self.policies)}")
        if not self.pers or not seeds:
            raise ConfigError("an experiment needs at least one PER and one seed")
        for p in self.pers:
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"PER must be in [0, 1], got {p}")
        if len(set(self.pers)) != len(self.pers) or len(set(seeds)) != len(seeds):
            raise ConfigError("PERs and seeds must not repeat")
        if self.duration_s is not None and self.duration_s <= 0:
            raise ConfigError(f"duration_s must be positive, got {self.duration_s}")
        for name, table in self.policy.items():
            if not isinstance(table, dict):
                raise ConfigError(f"[policy.{name}] must be a table")
        self._check_faults()

    def _check_faults(self) -> None:
        """Normalize ``faults`` (``halt:1@30.0`` -> ``halt:1@30``, as ``RunConfig`` does)
        and check them and ``security.auth``, each error one line naming the key and the value."""
        try:
            faults = fault_specs(self.faults)
        except ConfigError as exc:
            raise ConfigError(f"faults: {exc}") from None
        object.__setattr__(self, "faults", faults)
        check_auth(self.auth, key="auth:")

    @property
    def seed_values(self) -> tuple[int, ...]:
        """The seeds as a tuple (``seeds = N`` in a file, 0..N-1, is one once built)."""
        assert isinstance(self.seeds, tuple)
        return self.seeds

    # --- TOML ----------------------------------------------------------------------------

    def to_toml(self) -> str:
        """The experiment file for this config, every value written out."""
        data = to_dict(self)
        top = {k: v for k, v in data.items() if k not in ("convoy", "loss", "policy", "executor")}
        out: dict[str, Any] = {"experiment": top, "convoy": data["convoy"], "loss": data["loss"]}
        if self.policy:
            out["policy"] = {name: dict(table) for name, table in self.policy.items()}
        return dumps_toml(out)

    @classmethod
    def from_toml(cls, path: str | Path) -> ExperimentConfig:
        """Load an experiment file, strictly (unknown tables or keys are errors)."""
        data = load_toml(path)
        return cls.from_tables(data, str(path))

    @classmethod
    def from_tables(cls, data: dict[str, Any], where: str = "experiment") -> ExperimentConfig:
        unknown = set(data) - {"experiment", "convoy", "loss", "policy", "executor"}
        if unknown:
            raise ConfigError(
                f"{where}: unknown table(s) {', '.join(sorted(unknown))}; expected experiment, convoy, loss, policy, executor"
            )
        if "experiment" not in data:
            raise ConfigError(f"{where}: missing the [experiment] table")
        table = dict(data["experiment"])
        for key in ("convoy", "loss", "policy", "executor"):
            if key in table:
                raise ConfigError(f"{where}: {key} belongs in its own [{key}] table")
            if key in data:
                table[key] = data[key]
        config = from_dict(cls, table, where)
        from openconvoy.policies.spec import classical_from_table, plugin_from_table

        for name, policy_table in config.policy.items():  # referenced or not, checked here
            if isinstance(policy_table, dict) and "plugin" in policy_table:
                plugin_from_table(policy_table, f"{where}: policy.{name}")
            else:
                classical_from_table(policy_table, name, f"{where}: policy.{name}")
        return config

    # --- runs ----------------------------------------------------------------------------

    def run_configs(
        self, policy_specs: dict[str, str] | None = None
    ) -> list[tuple[str, RunConfig]]:
        """Every run as ``(policy label, RunConfig)``, ordered by policy, PER, seed.

        ``policy_specs`` maps a label to the spec to load (inline policies become files).
        """
        specs = policy_specs or {p: p for p in self.policies}
        out = []
        for label in self.policies:
            for per in self.pers:
                for seed in self.seed_values:
                    out.append(
                        (
                            label,
                            RunConfig(
                                scenario=self.scenario,
                                policy=specs[label],
                                per=per,
                                seed=seed,
                                duration_s=self.duration_s,
                                convoy=self.convoy,
                                loss=self.loss,
                                faults=self.faults,
                                auth=self.auth,
                            ),
                        )
                    )
        return out


def freeze(config: ExperimentConfig) -> ExperimentConfig:
    """``config`` with every classical policy file it names inlined as a ``[policy.STEM]``
    table (``path/fast.toml+ladder`` becomes ``fast+ladder``), so the run directory's copy
    of the experiment needs no other file and labels do not depend on where files were."""
    from openconvoy.policies.presets import PRESETS
    from openconvoy.policies.spec import classical_from_toml, plugin_of

    inline = dict(config.policy)
    labels = []
    for label in config.policies:
        spec = PolicySpec.parse(label)
        base = spec.base
        if not spec.toml:
            labels.append(label)
            continue
        if plugin_of(label) is None:
            classical_from_toml(base)  # validates the file
        table = dict(load_toml(base)["policy"])
        name = Path(base).stem
        table.setdefault("name", name)
        if name in PRESETS or (name in inline and inline[name] != table):
            raise ConfigError(
                f"policy file {base}: its name {name!r} is taken by a preset or another policy; rename the file"
            )
        inline[name] = table
        labels.append(str(spec.with_base(name)))
    if labels == list(config.policies):
        return config
    return dataclasses.replace(config, policies=tuple(labels), policy=inline)


def write_inline_policies(config: ExperimentConfig, out_dir: Path) -> dict[str, str]:
    """Write ``[policy.NAME]`` tables as policy files under ``out_dir/policies`` and map each
    policy label to the spec to load; check every spec loads (one clear error if not)."""
    files: dict[str, str] = {}
    for name, table in config.policy.items():
        if "/" in name or name.endswith(".toml"):
            raise ConfigError(f"[policy.{name}]: an inline policy name is a plain word")
        path = out_dir / "policies" / f"{name}.toml"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(dumps_toml({"policy": {"name": name, **table}}), encoding="utf-8")
        files[name] = str(path)
    specs: dict[str, str] = {}
    for label in config.policies:
        parsed = PolicySpec.parse(label)
        spec = str(parsed.with_base(files[parsed.base])) if parsed.base in files else label
        _check_loads(spec)  # fail before any process starts
        specs[label] = spec
    return specs


def _check_loads(spec: str) -> None:
    """A classical or plug-in policy spec that does not load fails here, in one line."""
    from openconvoy.policies.spec import classical_config, load_policy, plugin_of

    if PolicySpec.parse(spec).learned:
        return
    if plugin_of(spec) is not None:
        load_policy(spec)
    else:
        classical_config(spec)


def policy_dirname(label: str) -> str:
    """A directory name for a policy label (file specs: the file's stem; plug-ins: their
    name and arguments)."""
    spec = PolicySpec.parse(label)
    base = spec.base
    if spec.plugin:
        ref, _, args = base.partition("?")
        name = ref.rpartition(":")[2] + ("_" + args.replace("&", "_") if args else "")
        return "".join(c if c.isalnum() or c in "_.=-" else "_" for c in name)
    return (
        Path(base).stem.replace(" ", "_") + spec.suffix if ("/" in base or "." in base) else label
    )


def policy_dirnames(labels: Sequence[str]) -> dict[str, str]:
    """Each policy's directory name, distinct across ``labels``: two files with one stem
    (``runs/a/policy.zip``, ``runs/b/policy.zip``) get a short digest of their label each,
    so runs of different policies never share a directory."""
    names = {label: policy_dirname(label) for label in labels}
    taken: dict[str, int] = {}
    for name in names.values():
        taken[name] = taken.get(name, 0) + 1
    return {
        label: name
        if taken[name] == 1
        else f"{name}-{hashlib.sha256(label.encode()).hexdigest()[:8]}"
        for label, name in names.items()
    }


# --- running -----------------------------------------------------------------------------

RUN_FILES = batched_sweep.RUN_FILES


def run_series(log: mt.Columns, lengths: dict[int, float], max_points: int = 800) -> dict[str, Any]:
    """The time series the sweep figures draw, thinned to at most ``max_points`` ticks."""
    t, speed_diff = mt.speed_difference_series(log)
    _, max_err = mt.max_platooning_error_series(log)
    _, x = mt.aligned(log, "x_m", t)
    _, y = mt.aligned(log, "y_m", t)
    gaps = mt.follower_gaps(log)
    closest = np.full(len(t), np.nan)
    limit = math.inf
    for vid, (tg, g) in gaps.items():
        closest[np.searchsorted(t, tg)] = np.fmin(closest[np.searchsorted(t, tg)], g)
        limit = min(limit, 0.5 * (lengths.get(vid, 0.0) + lengths.get(vid - 1, 0.0)))
    step = max(1, int(math.ceil(len(t) / max_points)))
    sl = slice(None, None, step)
    return {
        "t": t[sl],
        "speed_diff": speed_diff[sl],
        "max_error": max_err[sl],
        "x": x[sl].T,
        "y": y[sl].T,
        "closest_gap": closest[sl],
        "collision_gap": limit if math.isfinite(limit) else 0.0,
    }


@dataclass
class SweepResult:
    """A finished sweep: its config, summary rows, per-run metrics and figure series
    (only the runs that finished; ``failures`` names the others; ``per_run``: policy
    label -> why its runs were not batched)."""

    config: ExperimentConfig
    rows: list[dict[str, Any]]
    runs: list[tuple[str, RunConfig, dict[str, Any]]]
    series: dict[tuple[str, float], dict[str, Any]]
    out_dir: Path
    failures: list[TaskFailure] = field(default_factory=list)
    per_run: dict[str, str] = field(default_factory=dict)


class SweepInterrupted(OpenConvoyError):
    """Ctrl-C or SIGTERM stopped a sweep: the finished runs are kept, no summary written."""

    def __init__(self, out: Path, kept: int, total: int) -> None:
        self.out, self.kept, self.total = out, kept, total
        super().__init__(
            f"interrupted: {kept} of {total} runs finished and are kept in {out}; "
            f"openconvoy experiment per-sweep --resume {out} runs the other {total - kept}"
        )


RESUME_DIR = ".resume"
"""Under a sweep's directory until it completes: each finished run's metrics and series."""


def run_experiment(
    config: ExperimentConfig,
    out_dir: str | Path,
    jobs: int | None = None,
    progress: bool = True,
    figures: bool = True,
    executor: ExecutorConfig | Executor | None = None,
    raise_on_failure: bool = True,
    run_logs: bool = True,
    say: Callable[[str], None] | None = None,
    resume: bool = False,
    compile_note: Callable[[str], None] | None = None,
) -> SweepResult:
    """Run every (policy, PER, seed) of ``config`` and write the run directory (see the
    module docstring). The runs are tasks of ``executor`` (default: ``config.executor``,
    the local processes, ``jobs`` of them if given): a policy's runs in a few batched
    tasks where its ``batched`` setting and the batched env allow (``batched.tasks``),
    else one task per run; ``say`` gets one line per policy not batched and why
    (default: stderr, with ``progress``). ``run_logs``: write every run's ``log.csv``
    (else only its ``metrics.json``; the summary is the same). When runs fail, the
    others' results are written all the same, ``summary.*`` covers them,
    ``failures.json`` names the lost runs, and ``TasksFailed`` is raised (or, without
    ``raise_on_failure``, the result lists them). ``resume``: ``out_dir`` holds this
    sweep, interrupted; only the runs it lacks are run (``SweepInterrupted`` when
    interrupted again). ``compile_note`` gets one line before the batched kernels' first
    compile (default: stderr, with ``progress``, on a terminal)."""
    config = freeze(config)
    _check_policies(config)
    _check_fault_vehicles(config)
    chosen, batched = _executor(config, executor, jobs)  # Ray: reached before any write
    out = Path(out_dir) if resume else _start_run_dir(config, Path(out_dir))
    planned = config.run_configs(write_inline_policies(config, out))
    names = policy_dirnames(config.policies)
    dirs = [run_dirname(label, rc, names[label]) for label, rc in planned]
    series = [rc.seed == config.seed_values[0] for _, rc in planned]
    if resume:
        per_run, run_logs = _load_records(out, dirs)
    else:
        per_run = _clear_records(out, len(dirs), run_logs)
    todo = [i for i, res in enumerate(per_run) if res is None]
    slots = chosen.slots if isinstance(chosen, Executor) else chosen.jobs or available_cores()
    tasks = batched_sweep.plan(
        [planned[i] for i in todo], [dirs[i] for i in todo], [series[i] for i in todo],
        slots, batched, run_logs,
    )  # fmt: skip
    if say is None and progress:
        say = _stderr_line
    batched_sweep.say_per_run(tasks, say or (lambda line: None))
    if len(tasks.tasks) < len(todo):  # some runs batched: their kernels may compile first
        _say_compile(compile_note or (_stderr_line if progress and _on_terminal() else None))
    if isinstance(chosen, ExecutorConfig):  # local: no more processes than tasks
        chosen = make_executor(
            dataclasses.replace(chosen, jobs=max(1, min(slots, len(tasks.tasks))))
        )

    def keep(k: int, value: Any) -> None:
        """Task ``k`` ended: write its runs' files and records at once."""
        first, n = tasks.spans[k]
        for j, res in enumerate(
            batched_sweep.expand_one(value, n, [dirs[i] for i in todo[first : first + n]])
        ):
            i = todo[first + j]
            per_run[i] = res
            if not isinstance(res, TaskFailure):
                _write_run(out, dirs[i], i, res)

    previous = signal.getsignal(signal.SIGTERM)
    in_main = _in_main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, _raise_interrupt)  # SIGTERM keeps the runs as Ctrl-C does
    try:
        with chosen:
            runs_of = [n for _, n in tasks.spans]  # the bar counts runs, a batch its runs
            chosen.map(tasks.tasks, progress, desc=config.name, on_result=keep, weights=runs_of)
    except KeyboardInterrupt:
        kept = sum(1 for r in per_run if r is not None and not isinstance(r, TaskFailure))
        raise SweepInterrupted(out, kept, len(planned)) from None
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    runs, failures, kept_series = _collect(planned, per_run)
    result = SweepResult(config, [], runs, kept_series, out, failures, tasks.per_run)
    return _finish(result, figures, raise_on_failure)


def _on_terminal() -> bool:
    import sys

    return sys.stderr.isatty()


def _say_compile(say: Callable[[str], None] | None) -> None:
    """The batched kernels' first compile, said before the wait it causes."""
    if say is None:
        return
    try:
        from openconvoy.envs.vector.jit import first_compile_note
    except ImportError:  # no numba: nothing is batched anyway
        return
    note = first_compile_note()
    if note is not None:
        say(note)


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _record_path(out: Path, i: int) -> Path:
    return out / RESUME_DIR / f"run-{i:06d}.pkl"


def _clear_records(out: Path, n: int, run_logs: bool) -> list[Any]:
    """A fresh sweep: no records of an earlier one in ``out`` (its options kept for a
    resume); no run finished."""
    shutil.rmtree(out / RESUME_DIR, ignore_errors=True)
    (out / RESUME_DIR).mkdir()
    (out / RESUME_DIR / "options.json").write_text(json.dumps({"run_logs": run_logs}) + "\n")
    return [None] * n


def _load_records(out: Path, dirs: Sequence[str]) -> tuple[list[Any], bool]:
    """What an interrupted sweep in ``out`` finished: per run, its record (metrics and
    series) where its record and files are there, else None (to run); and whether it
    writes run logs."""
    if not (out / "experiment.toml").is_file():
        raise ConfigError(f"--resume: {out} holds no sweep (no experiment.toml)")
    if not (out / RESUME_DIR).is_dir():
        raise ConfigError(
            f"--resume: {out} holds no interrupted sweep (it is complete or was not started)"
        )
    found: list[Any] = [None] * len(dirs)
    for i, d in enumerate(dirs):
        path = _record_path(out, i)
        if not path.is_file() or not (out / d / "metrics.json").is_file():
            continue
        with path.open("rb") as f:  # our own file, written by this sweep's driver
            record = pickle.load(f)
        if record.get("dir") == d:
            found[i] = record
    options = json.loads((out / RESUME_DIR / "options.json").read_text())
    return found, bool(options.get("run_logs", True))


def _write_run(out: Path, d: str, i: int, res: dict[str, Any]) -> None:
    """A finished run's files, then its record (the record last: it says the files are whole)."""
    run_dir = out / d
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, data in res["files"].items():
        (run_dir / name).write_bytes(data)
    path = _record_path(out, i)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        pickle.dump({"dir": d, "metrics": res["metrics"], "series": res["series"]}, f)
    os.replace(tmp, path)


def _collect(
    planned: Sequence[tuple[str, RunConfig]], per_run: Sequence[Any]
) -> tuple[
    list[tuple[str, RunConfig, dict[str, Any]]],
    list[TaskFailure],
    dict[tuple[str, float], dict[str, Any]],
]:
    """Each finished run's metrics, the failures, the figure series, in run order."""
    runs, failures = [], []
    series = {}
    for (label, rc), res in zip(planned, per_run):
        if isinstance(res, TaskFailure):
            failures.append(res)
            continue
        runs.append((label, rc, res["metrics"]))
        if res["series"] is not None:
            series[(label, rc.per)] = res["series"]
    return runs, failures, series


def _check_policies(config: ExperimentConfig) -> None:
    """Fail before anything is written on a classical policy that does not load."""
    for label in config.policies:
        spec = PolicySpec.parse(label)
        if spec.base not in config.policy:
            _check_loads(label)


def _check_fault_vehicles(config: ExperimentConfig) -> None:
    """Fail before anything is written on a fault naming a vehicle the convoy lacks."""
    if not config.faults:
        return
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.envs.vehicles import vehicle_preset

    presets = [vehicle_preset(v) for v in config.convoy.vehicles] or None
    scenario = make_scenario(config.scenario, config.convoy.n_followers, presets)
    faults = tuple(parse_fault(f) for f in config.faults)
    check_faults(faults, scenario.n_vehicles)
    check_fault_times(faults, config.duration_s or scenario.duration_s)


def _executor(
    config: ExperimentConfig, executor: ExecutorConfig | Executor | None, jobs: int | None
) -> tuple[ExecutorConfig | Executor, bool | None]:
    """The executor (Ray's made now; local processes once the tasks are known) and the
    ``batched`` setting."""
    if isinstance(executor, Executor):
        return executor, config.executor.batched
    chosen = executor or config.executor
    if jobs is not None and chosen.jobs is None:
        chosen = dataclasses.replace(chosen, jobs=jobs)
    return (make_executor(chosen) if chosen.kind == "ray" else chosen), chosen.batched


def _stderr_line(line: str) -> None:
    import sys

    print(line, file=sys.stderr)


def _start_run_dir(config: ExperimentConfig, out: Path) -> Path:
    """The run directory with the experiment's copy and the manifest."""
    from openconvoy import __version__

    out.mkdir(parents=True, exist_ok=True)
    (out / "experiment.toml").write_text(config.to_toml(), encoding="utf-8")
    write_json(
        out / "manifest.json",
        {
            "openconvoy_version": __version__,
            "experiment": "experiment.toml",
            "rerun": f"openconvoy experiment per-sweep --config {out / 'experiment.toml'} --out NEW_DIR",
        },
    )
    return out


def _finish(result: SweepResult, figures: bool, raise_on_failure: bool) -> SweepResult:
    """Summaries, ``failures.json`` (raising ``TasksFailed``) or the figures."""
    config, out, failures = result.config, result.out_dir, result.failures
    result.rows = summarize(result.runs, config.policies, config.pers)
    _write_summary(out, result.rows, complete=not failures)
    if failures:
        write_json(out / "failures.json", {"failures": [dataclasses.asdict(f) for f in failures]})
        if raise_on_failure:
            raise TasksFailed(
                failures,
                len(failures) + len(result.runs),
                f"the other {len(result.runs)} are in {out} (summary.csv covers only them)",
            )
        return result
    if figures:
        from openconvoy.experiments import figures as figs

        figs.sweep_figures(result, out)
    return result


def _write_summary(out: Path, rows: list[dict[str, Any]], complete: bool) -> None:
    """``summary.json`` and ``summary.csv``, whole or not at all: each written aside and
    renamed, with SIGINT/SIGTERM held until both are (then ``.resume/`` goes, when the
    sweep is ``complete``)."""
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        for name, text in (
            ("summary.csv", summary_csv(rows)),
            ("summary.json", json.dumps(mt.json_safe({"rows": rows}), indent=2) + "\n"),
        ):
            tmp = out / f".{name}.tmp"
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, out / name)
        if complete:
            shutil.rmtree(out / RESUME_DIR, ignore_errors=True)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def run_dirname(label: str, config: RunConfig, policy_dir: str | None = None) -> str:
    """A run's directory under the sweep's: ``runs/<policy>/per_<PER>/seed_<seed>``
    (``policy_dir``: the policy's directory name, default ``policy_dirname(label)``)."""
    name = policy_dir or policy_dirname(label)
    return f"runs/{name}/per_{_per_name(config.per)}/seed_{config.seed}"


def _per_name(per: float) -> str:
    """``0.60`` for two-decimal PERs (sorts well), else every digit needed (``0.125``)."""
    return f"{per:.2f}" if round(per, 2) == per else f"{per:g}"


# --- summaries ---------------------------------------------------------------------------


def stats(values: Sequence[float]) -> dict[str, float]:
    """Mean, population standard deviation, min and max of the finite values (NaN if none)."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if not len(v):
        return dict.fromkeys(STATS, math.nan)
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def summarize(
    runs: Sequence[tuple[str, RunConfig, dict[str, Any]]],
    policies: Sequence[str],
    pers: Sequence[float],
) -> list[dict[str, Any]]:
    """One row per (policy, PER): ``{"per", "policy", "runs", <metric>: {mean, std, min, max}}``."""
    rows = []
    for label in policies:
        for per in pers:
            group = [m for lab, rc, m in runs if lab == label and rc.per == per]
            row: dict[str, Any] = {"per": float(per), "policy": label, "runs": len(group)}
            for key in mt.METRIC_KEYS:
                row[key] = stats([float(m[key]) if m[key] is not None else math.nan for m in group])
            rows.append(row)
    return rows


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else format(v, ".10g")
    return str(v)


def summary_csv(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as CSV: policy, per, runs, then ``<metric>_<stat>`` columns."""
    header = ["policy", "per", "runs"] + [f"{k}_{s}" for k in mt.METRIC_KEYS for s in STATS]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(
            [r["policy"], _fmt(r["per"]), r["runs"]]
            + [_fmt(r[k][s]) for k in mt.METRIC_KEYS for s in STATS]
        )
    return buf.getvalue()


def read_summary(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a sweep's ``summary.json`` (a file or its run directory); NaN for null."""
    p = Path(path)
    if p.is_dir():
        p = p / "summary.json"
    data = json.loads(p.read_text(encoding="utf-8"))
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list):
        raise ConfigError(f"{p}: not a sweep summary (no 'rows' list)")
    for r in rows:
        for k in mt.METRIC_KEYS:
            if isinstance(r.get(k), dict):
                r[k] = {s: (math.nan if r[k].get(s) is None else float(r[k][s])) for s in STATS}
        r.setdefault("policy", "")
    return rows


def with_overrides(config: ExperimentConfig, **changes: Any) -> ExperimentConfig:
    """``config`` with top-level fields changed (``convoy``/``loss`` fields by name too)."""
    convoy_keys = {f.name for f in dataclasses.fields(ConvoySection)}
    loss_keys = {f.name for f in dataclasses.fields(LossSection)}
    convoy = {k: v for k, v in changes.items() if k in convoy_keys}
    loss = {k: v for k, v in changes.items() if k in loss_keys}
    top = {k: v for k, v in changes.items() if k not in convoy_keys | loss_keys}
    return dataclasses.replace(
        config,
        **top,
        convoy=dataclasses.replace(config.convoy, **convoy),
        loss=dataclasses.replace(config.loss, **loss),
    )
