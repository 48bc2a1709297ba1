"""``openconvoy tune``: Optuna search over a classical policy's parameters.

Each trial is a ClassicalConfig (the base policy with some parameters changed), written
as a policy TOML file and run with the experiments' ``run_sim`` on every (PER, seed) of
the evaluation grid, exactly as ``openconvoy sim --policy FILE`` would run it. The
objective, to minimize, is

    mean over runs of p95_platooning_error_m  +  collision_penalty_m * collisions per run
    + speed_difference_weight * mean over runs of mean_speed_difference_mps

so a collision outweighs any spacing gain. Every grid run may carry injected faults and
an ``security.auth`` setting (``--fault``, ``--auth``; ``TuneConfig.faults``), so a controller can be
tuned for robustness to, say, a predecessor braking hard (``halt:1@30``). The best trial is written as a TOML policy
file (``classical_to_toml``) that ``--policy`` accepts.

Parameters (``PARAMETERS``; names are dotted ClassicalConfig paths): the speed
controller's gains (``speed.kp``, ``speed.kd``, ``speed.ki`` for ``pid``), the heading
controller's gain (``heading.gain`` for Stanley, ``heading.lookahead_s`` for pure
pursuit), the ``mpc`` family's weights in place of the gains (``mpc.w_gap``, ``mpc.w_speed``,
``mpc.w_du``, ``mpc.w_accel``, ``mpc.w_terminal``) and the spacing policy's shape (``member.spacing.headway_s``,
``member.spacing.standstill_m`` for time-headway policies). A constant-distance policy's
``distance_m`` is the specification, not a tunable: it is left alone.

Plug-ins (docs/your-controller.md): a classical policy's plug-in components add the
parameters their classes declare (``tunable = {"headway_s": (0.3, 2.0)}``) as
``member.spacing.params.headway_s`` (``member.trigger.params.*``, ``speed.params.*``,
``heading.params.*``, ``member.topology_params.*``); a whole-policy plug-in base
(``--policy file.py:Name``) is tuned over its declared keyword arguments, ``args.NAME``,
each trial a policy TOML naming the plug-in with its ``[policy.args]``.
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

from openconvoy.core import plugins
from openconvoy.core.config import dumps_toml
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import check_auth, fault_specs
from openconvoy.policies.classical import ClassicalConfig
from openconvoy.policies.spec import classical_config, classical_to_toml, plugin_of


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
        # the mpc family's weights (``core.mpc.MPCConfig``)
        Param("mpc.w_gap", 0.05, 20.0, log=True),
        Param("mpc.w_speed", 0.05, 20.0, log=True),
        Param("mpc.w_du", 0.01, 20.0, log=True),
        Param("mpc.w_accel", 0.001, 5.0, log=True),
        Param("mpc.w_terminal", 1.0, 100.0, log=True),
    )
}


@dataclass(frozen=True)
class PluginConfig:
    """A whole-policy plug-in and its keyword arguments: what ``tune`` varies for one."""

    plugin: str
    args: dict[str, Any] = field(default_factory=dict)
    name: str = "tuned"
    description: str = ""


Candidate = ClassicalConfig | PluginConfig


def base_candidate(spec: str) -> Candidate:
    """What ``tune`` starts from: a classical policy's config, or a plug-in with its arguments."""
    plugin = plugin_of(spec)
    if plugin is None:
        return classical_config(spec)
    ref, kwargs, label = plugin
    return PluginConfig(plugins.split_args(ref)[0], {**plugins.split_args(ref)[1], **kwargs}, label)


def candidate_toml(candidate: Candidate) -> str:
    """The policy file of a candidate (``--policy`` reads it back)."""
    if isinstance(candidate, ClassicalConfig):
        return classical_to_toml(candidate)
    table: dict[str, Any] = {"plugin": candidate.plugin, "name": candidate.name}
    if candidate.args:
        table["args"] = dict(candidate.args)
    return dumps_toml({"policy": table})


def parameters_of(config: Candidate) -> dict[str, Param]:
    """Every parameter ``tune`` may search for ``config``: ``PARAMETERS`` and what its
    plug-ins declare tunable."""
    if isinstance(config, PluginConfig):
        declared = plugins.tunable(plugins.resolve(config.plugin, "policy", config.plugin)[0])
        return {f"args.{n}": Param(f"args.{n}", lo, hi) for n, (lo, hi) in declared.items()}
    out = dict(PARAMETERS)
    m = config.member
    parts: list[tuple[str, str, str]] = [
        ("member.spacing.params", "spacing", m.spacing.kind),
        ("member.trigger.params", "trigger", m.trigger.kind),
        ("speed.params", "speed", config.speed.kind),
        ("heading.params", "heading", config.heading.kind),
    ]
    from openconvoy.core.gates import is_plugin_topology

    if is_plugin_topology(m.topology):
        parts.append(("member.topology_params", "topology", m.topology))
    for prefix, kind, spec in parts:
        if kind == "topology" or _is_plugin_kind(config, kind):
            for n, (lo, hi) in plugins.component_tunable(kind, spec, spec).items():
                out[f"{prefix}.{n}"] = Param(f"{prefix}.{n}", lo, hi)
    return out


def _is_plugin_kind(config: ClassicalConfig, kind: str) -> bool:
    m = config.member
    return {
        "spacing": m.spacing.is_plugin,
        "trigger": m.trigger.is_plugin,
        "speed": config.speed.is_plugin,
        "heading": config.heading.is_plugin,
    }[kind]


def applicable(config: Candidate) -> list[str]:
    """The parameters that mean something for ``config``'s controllers and spacing (a
    plug-in's: those it declares tunable)."""
    declared = [p for p in parameters_of(config) if p not in PARAMETERS]
    if isinstance(config, PluginConfig):
        return declared
    out = []
    if config.mpc is not None:  # the mpc family: its weights in place of the PD gains
        out += ["mpc.w_gap", "mpc.w_speed", "mpc.w_du", "mpc.w_accel", "mpc.w_terminal"]
    elif not config.speed.is_plugin:
        out += ["speed.kp", "speed.kd"]
        if config.speed.kind == "pid":
            out.append("speed.ki")
    if not config.heading.is_plugin:
        out.append("heading.gain" if config.heading.kind == "stanley" else "heading.lookahead_s")
    spacing = config.member.spacing
    if not spacing.is_plugin and spacing.kind != "constant-distance":
        out += ["member.spacing.headway_s", "member.spacing.standstill_m"]
    return out + declared


def with_values(config: Candidate, values: dict[str, float], name: str) -> Candidate:
    """``config`` with dotted-path ``values`` replaced, renamed ``name``."""
    out = dataclasses.replace(config, name=name)
    for path, value in values.items():
        out = _replace_path(out, path.split("."), value)
    return out


def _replace_path(obj: Any, parts: list[str], value: float) -> Any:
    if isinstance(obj, dict):  # a plug-in's keyword arguments
        if len(parts) == 1:
            return {**obj, parts[0]: float(value)}
        return {**obj, parts[0]: _replace_path(obj.get(parts[0], {}), parts[1:], value)}
    if (
        not dataclasses.is_dataclass(obj)
        or isinstance(obj, type)
        or parts[0] not in {f.name for f in dataclasses.fields(obj)}
    ):
        raise ConfigError(f"unknown parameter path component {parts[0]!r}")
    if len(parts) == 1:
        return dataclasses.replace(obj, **{parts[0]: float(value)})
    return dataclasses.replace(
        obj, **{parts[0]: _replace_path(getattr(obj, parts[0]), parts[1:], value)}
    )


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
        faults: injected faults of every run, ``KIND:VEHICLE@T_S`` (``core.faults``): a
            controller tuned for robustness to, say, a braking predecessor (``halt:1@30``).
        auth: ``"required"`` (members reject forged messages) or ``"off"``.
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
    faults: tuple[str, ...] = ()
    auth: str = "required"
    params: tuple[str, ...] = ()
    collision_penalty_m: float = 100.0
    speed_difference_weight: float = 1.0
    seed: int = 0
    name: str = "tuned"

    def __post_init__(self) -> None:
        for name in ("pers", "seeds", "params"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        object.__setattr__(self, "faults", fault_specs(self.faults))
        check_auth(self.auth)
        if self.trials < 1 or not self.pers or not self.seeds:
            raise ConfigError("tune needs at least one trial, one PER and one seed")
        unknown = [p for p in self.params if p not in PARAMETERS and not _plugin_path(p)]
        if unknown:
            raise ConfigError(
                f"unknown tuning parameter(s) {', '.join(unknown)}; expected some of {', '.join(PARAMETERS)}"
            )


def _plugin_path(path: str) -> bool:
    """A dotted path into a plug-in's keyword arguments (checked against what it
    declares tunable once the base is loaded)."""
    return path.startswith(("args.", "member.topology_params.")) or ".params." in path


@dataclass
class TuneResult:
    """The best configuration, its objective and the per-trial history (every finished
    trial of the study, earlier sessions' too); ``evaluated``: trials this call ran,
    ``requeued``: trials a stopped driver had left running, ``failures``: evaluations
    that failed (TaskFailure)."""

    best: Candidate
    best_value: float
    best_params: dict[str, float]
    base_value: float
    history: list[dict[str, Any]] = field(default_factory=list)
    study_name: str = ""
    evaluated: int = 0
    requeued: int = 0
    failures: list[Any] = field(default_factory=list)


Evaluate = Callable[[Candidate], float]


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


def grid_runs(config: TuneConfig, policy: str) -> list[Any]:
    """The evaluation grid's ``RunConfig``s for ``policy`` (a spec), by PER then seed."""
    from openconvoy.experiments.runs import RunConfig

    return [
        RunConfig(
            scenario=config.scenario,
            policy=policy,
            per=per,
            seed=seed,
            duration_s=config.duration_s,
            faults=config.faults,
            auth=config.auth,
        )
        for per in config.pers
        for seed in config.seeds
    ]


def grid_evaluator(config: TuneConfig, workdir: Path, batched: bool = False) -> Evaluate:
    """Evaluate a candidate over ``config``'s PER x seed grid: ``run_sim`` on each run,
    or (``batched``) all of them in one ``VectorConvoyEnv`` (``experiments.batched.run``;
    the same metrics, to the bit, for the classical policies tuned here)."""
    from openconvoy.experiments.batched.run import run_batch
    from openconvoy.experiments.runs import run_sim

    counter = iter(range(1_000_000))

    def evaluate(candidate: Candidate) -> float:
        path = workdir / f"trial_{next(counter)}.toml"
        path.write_text(candidate_toml(candidate), encoding="utf-8")
        runs = grid_runs(config, str(path))
        if batched:
            metrics = [r["metrics"] for r in run_batch(runs, read_back=False, logs=False)]
        else:
            metrics = [run_sim(rc).metrics for rc in runs]
        return objective_of(metrics, config)

    return evaluate


def evaluate_on_worker(
    config: TuneConfig, files: dict[str, bytes], candidate: Candidate, batched: bool = False
) -> float:
    """Task: ``candidate``'s objective over the grid, in a temporary directory of the
    worker (``files``: the scenario's track file, if any, shipped from the driver)."""
    from openconvoy.experiments import portable

    with tempfile.TemporaryDirectory(prefix="openconvoy-tune-") as tmp:
        where = portable.land(files, tmp)
        local = dataclasses.replace(config, scenario=portable.relocate(config.scenario, where))
        with portable.driver_names(where):
            return grid_evaluator(local, Path(tmp), batched)(candidate)


def check_grid(config: TuneConfig) -> None:
    """Fail before any trial on a grid run that does not load (a fault naming a vehicle
    the convoy lacks, say): one ConfigError line, not a failed study."""
    from openconvoy.experiments.runs import build_env

    build_env(grid_runs(config, config.base)[0])


def grid_batched(config: TuneConfig, batched: bool | None = None) -> tuple[bool, str | None]:
    """Whether trials run their grid batched (``batched``: None = where exact, the
    ``[executor] batched`` setting) and, when they might have but do not, why not."""
    from openconvoy.experiments.batched.run import refusal

    if batched is False:
        return False, None
    why = refusal(grid_runs(config, config.base)[0], exact=batched is None)
    return why is None, why


# What a resumed study must share with the one it continues (the objective's definition).
STUDY_KEYS = (
    "base",
    "pers",
    "seeds",
    "scenario",
    "duration_s",
    "faults",
    "auth",
    "params",
    "collision_penalty_m",
    "speed_difference_weight",
)
# Settings a study recorded before they existed: the values it then ran with.
STUDY_DEFAULTS: dict[str, Any] = {"faults": [], "auth": "required"}
STUDY_ATTR = "openconvoy_tune"
BASE_ATTR = "openconvoy_base_value"


def open_storage(storage: str | None) -> Any:
    """Optuna storage: None (in memory), an RDB URL (``sqlite:///study.db``,
    ``postgresql://...``) or a journal file path (``study.journal``, anything without
    ``://``), all opened by this driver only."""
    if storage is None or "://" in storage:
        return storage
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    Path(storage).parent.mkdir(parents=True, exist_ok=True)
    return JournalStorage(JournalFileBackend(storage))


def _sampler(config: TuneConfig, resumed_trials: int, parallel: bool) -> Any:
    import optuna

    # A resumed study must not redraw the first session's random trials: the same seed
    # would, so the sampler's seed also takes the number of trials already in the study.
    seed = (
        config.seed
        if not resumed_trials
        else int(np.random.SeedSequence([config.seed, resumed_trials]).generate_state(1)[0])
    )
    # constant_liar: trials in flight count as pessimistic guesses, so parallel workers
    # do not all sample the same region (Optuna's advice for distributed TPE).
    return optuna.samplers.TPESampler(seed=seed, constant_liar=parallel)


def _open_study(
    config: TuneConfig, study_name: str, storage: Any, parallel: bool
) -> tuple[Any, int]:
    """The study (created, or loaded to resume) and how many trials it already held."""
    import optuna

    settings = json.loads(json.dumps({k: getattr(config, k) for k in STUDY_KEYS}))
    existing = 0
    if storage is not None:
        try:
            existing = len(optuna.load_study(study_name=study_name, storage=storage).trials)
        except KeyError:
            existing = 0
    study = optuna.create_study(
        study_name=study_name,
        storage=storage,
        direction="minimize",
        sampler=_sampler(config, existing, parallel),
        load_if_exists=True,
    )
    recorded = study.user_attrs.get(STUDY_ATTR)
    if recorded is not None:
        recorded = {**STUDY_DEFAULTS, **recorded}
    if recorded is None:
        study.set_user_attr(STUDY_ATTR, settings)
    elif recorded != settings:
        differ = ", ".join(k for k in STUDY_KEYS if recorded.get(k) != settings.get(k))
        raise ConfigError(
            f"study {study_name!r} was made with other settings ({differ}); "
            "use another --study-name or the same settings"
        )
    return study, existing


def _requeue_orphans(study: Any, params: list[str]) -> int:
    """Trials left running by a driver that was stopped: failed, and the candidates among
    them queued again, so each is evaluated once and finished trials are never repeated.
    A trial stopped before all its ``params`` were drawn was never sent for evaluation,
    so it is only failed. Returns how many were queued again. Assumes one driver per
    study at a time."""
    from optuna.trial import TrialState

    requeued = 0
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        study.tell(t.number, state=TrialState.FAIL)
        if set(params) <= set(t.params):
            study.enqueue_trial(t.params, user_attrs={"requeued_from": t.number})
            requeued += 1
    return requeued


def tune(
    config: TuneConfig,
    evaluate: Evaluate | None = None,
    progress_bar: bool = False,
    executor: Any = None,
    study_name: str | None = None,
    storage: str | None = None,
    say: Callable[[str], None] | None = None,
) -> TuneResult:
    """Run the study until it holds ``config.trials`` finished trials.

    Each trial is a task of ``executor`` (an ``ExecutorConfig`` or ``Executor``; default:
    in this process), with up to its ``slots`` trials in flight, its grid batched unless
    the executor config's ``batched`` is False or the batched env refuses it (``say``
    gets one line why; default stderr, with ``progress_bar``); ``evaluate`` (an
    in-process callable, for tests) replaces the simulated grid and runs here. With
    ``storage`` (see ``open_storage``) the study persists under ``study_name`` (default
    ``config.name``): a later call with the same name and storage resumes it, running only
    the trials still missing (those a stopped driver left running are evaluated again
    once, if their parameters were all drawn).
    """
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    base = base_candidate(config.base)
    if evaluate is None and config.faults:
        check_grid(config)
    table = parameters_of(base)
    params = list(config.params) or applicable(base)
    unknown = [p for p in params if p not in table]
    if unknown or not params:
        raise ConfigError(
            f"tune: {config.base} has no tunable parameter {', '.join(unknown)}; expected some "
            f"of {', '.join(table) or 'none (declare tunable = {name: (low, high)} on the plug-in)'}"
        )
    fn = evaluate or _grid_task(config, executor, say or (_stderr if progress_bar else None))
    executor = _executor_for(executor, evaluate is not None)
    study_name = study_name or config.name
    failures: list[Any] = []
    with executor:
        study, existing = _open_study(config, study_name, open_storage(storage), executor.slots > 1)
        requeued = _requeue_orphans(study, params)
        base_value = _base_value(study, executor, fn, base, config.name)
        if not existing:
            # The base's own values first: the study can only improve on the starting point.
            study.enqueue_trial(
                {p: _get_path(base, p) for p in params if _in_range(base, p, table)}
            )
        done = len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))
        todo = max(0, config.trials - done)
        evaluated = _ask_tell(
            study, executor, fn, base, params, config.name, todo, progress_bar, failures, table
        )
    result = _result(study, base, config, study_name, base_value, failures)
    result.evaluated, result.requeued, result.failures = evaluated, requeued, failures
    return result


def _stderr(line: str) -> None:
    import sys

    print(line, file=sys.stderr)


def _grid_task(
    config: TuneConfig, executor: Any, say: Callable[[str], None] | None
) -> Callable[[Candidate], float]:
    """The trials' task function: the grid on a worker, batched where it may be."""
    import functools

    from openconvoy.experiments import portable
    from openconvoy.experiments.executor import ExecutorConfig

    asked = executor.batched if isinstance(executor, ExecutorConfig) else None
    batched, why = grid_batched(config, asked)
    if why is not None and say is not None:
        say(f"tune: one ConvoyEnv per run of each trial ({why})")
    files = portable.ship([config.scenario])
    return functools.partial(evaluate_on_worker, config, files, batched=batched)


def _executor_for(executor: Any, in_process: bool) -> Any:
    from openconvoy.experiments.executor import Executor, LocalExecutor, make_executor

    if in_process or executor is None:
        return LocalExecutor(jobs=1)
    return executor if isinstance(executor, Executor) else make_executor(executor)


def _base_value(study: Any, executor: Any, fn: Any, base: Candidate, name: str) -> float:
    """The base policy's objective: the study's record of it, or evaluated now."""
    from openconvoy.experiments.executor import Task, TaskFailure, TasksFailed

    recorded = study.user_attrs.get(BASE_ATTR)
    if recorded is not None:
        return float(recorded)
    _, value = _run_alone(executor, Task("base policy", fn, dataclasses.replace(base, name=name)))
    if isinstance(value, TaskFailure):
        raise TasksFailed(
            [value], 1, "the base policy's evaluation is the study's reference", "trials"
        )
    study.set_user_attr(BASE_ATTR, float(value))
    return float(value)


def _result(
    study: Any,
    base: Candidate,
    config: TuneConfig,
    study_name: str,
    base_value: float,
    failures: list[Any],
) -> TuneResult:
    """The study's best trial as a policy, with the history of every finished trial."""
    from optuna.trial import TrialState

    from openconvoy.experiments.executor import TasksFailed

    complete = sorted(
        study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)), key=lambda t: t.number
    )
    if not complete:
        raise TasksFailed(
            failures, len(failures), f"no trial of study {study_name!r} finished", "trials"
        )
    history = [
        {"trial": t.number, "value": float(t.value), **{p: float(v) for p, v in t.params.items()}}
        for t in complete
    ]
    best_trial = min(complete, key=lambda t: (t.value, t.number))
    best_params = {k: float(v) for k, v in best_trial.params.items()}
    described = ", ".join(f"{k} {v:.4g}" for k, v in best_params.items())
    best = dataclasses.replace(
        with_values(base, best_params, config.name),
        description=f"{config.base} tuned by openconvoy tune ({len(complete)} trials, PER "
        f"{', '.join(f'{p:g}' for p in config.pers)}, {len(config.seeds)} seeds{_under(config)}): "
        f"{described}",
    )
    return TuneResult(
        best, float(best_trial.value), best_params, float(base_value), history, study_name
    )


def _under(config: TuneConfig) -> str:
    """``", faults halt:1@30, auth off"``: what the grid ran under, for the description."""
    out = f", faults {' '.join(config.faults)}" if config.faults else ""
    return out + (", auth off" if config.auth == "off" else "")


def _run_alone(executor: Any, task: Any) -> tuple[Any, Any]:
    executor.submit(task)
    return executor.wait_one()


def _ask_tell(
    study: Any,
    executor: Any,
    fn: Callable[[Candidate], float],
    base: Candidate,
    params: list[str],
    name: str,
    todo: int,
    progress_bar: bool,
    failures: list[Any],
    table: dict[str, Param] = PARAMETERS,
) -> int:
    """Ask ``todo`` trials, at most ``executor.slots`` in flight, telling each result as
    it comes; failed evaluations are told as failed and collected in ``failures``."""
    from tqdm import tqdm

    from openconvoy.experiments.executor import Task, TaskFailure

    in_flight: dict[int, Any] = {}
    asked = 0
    with tqdm(total=todo, unit="trial", desc="tune", disable=not progress_bar) as bar:
        while asked < todo or in_flight:
            while asked < todo and len(in_flight) < executor.slots:
                trial = study.ask()
                values = {
                    p: trial.suggest_float(p, table[p].low, table[p].high, log=table[p].log)
                    for p in params
                }
                task = Task(f"trial {trial.number}", fn, with_values(base, values, name))
                executor.submit(task)
                in_flight[id(task)] = trial
                asked += 1
            task, value = executor.wait_one()
            trial = in_flight.pop(id(task))
            if isinstance(value, TaskFailure):
                from optuna.trial import TrialState

                study.tell(trial, state=TrialState.FAIL)
                failures.append(value)
            else:
                study.tell(trial, float(value))
            bar.update(1)
    return asked


def _get_path(config: Candidate, path: str) -> float:
    """The value at a dotted path (NaN: a plug-in argument left at its default)."""
    obj: Any = config
    for part in path.split("."):
        obj = obj.get(part, math.nan) if isinstance(obj, dict) else getattr(obj, part)
    return float(obj)


def _in_range(config: Candidate, path: str, table: dict[str, Param] = PARAMETERS) -> bool:
    p = table[path]
    return p.low <= _get_path(config, path) <= p.high


def write_tuned(result: TuneResult, out: str | Path) -> Path:
    """Write the best policy as TOML (``--policy`` accepts it) and ``<out>.json`` with
    the study's numbers next to it."""
    out = Path(out)
    if out.suffix != ".toml":
        raise ConfigError(f"{out}: the tuned policy is a .toml file")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(candidate_toml(result.best), encoding="utf-8")
    summary = {
        "best_value": result.best_value,
        "base_value": result.base_value,
        "best_params": result.best_params,
        "study_name": result.study_name,
        "evaluated_this_run": result.evaluated,
        "requeued": result.requeued,
        "failed": [f.line() for f in result.failures],
        "trials": result.history,
    }
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
    return out
