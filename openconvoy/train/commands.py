"""The handlers of ``openconvoy train``, ``tune`` and ``export`` (parsers in ``openconvoy.train.cli``)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from openconvoy.core.errors import ConfigError
from openconvoy.train.config import PPOConfig, TrainConfig, load_train_config, run_defaults
from openconvoy.train.randomization import (
    ABSOLUTE_ACTION_BOUNDS,
    RESIDUAL_ACTION_BOUNDS,
    SCRATCH_REWARD,
    TRAIN_REWARD,
    EnvSpec,
)


def train_config_from_args(args: argparse.Namespace, path: str | None = None) -> TrainConfig:
    """``path`` (a ``--config``; default the first, or the defaults) with the flags given
    on the command line applied."""
    if path is None and args.config:
        path = args.config[0]
    config = load_train_config(path) if path else TrainConfig()
    top: dict = {}
    for flag, key in (
        ("algo", "algo"),
        ("steps", "total_steps"),
        ("seed", "seed"),
        ("envs", "n_envs"),
        ("threads", "torch_threads"),
        ("vec_env", "vec_env"),
        ("worlds", "n_worlds"),
        ("budget", "budget_s"),
    ):
        if getattr(args, flag) is not None:
            top[key] = getattr(args, flag)
    env = config.env
    env_changes: dict = {}
    if args.base is not None:
        # A new base brings its own member config and rate unless they are given too.
        base = "" if args.base == "none" else args.base
        env_changes.update(base_policy=base, member=None, control_rate_hz=None)
        env_changes.update(_kind_defaults(env, bool(base)))
    if args.followers is not None:
        env_changes["n_followers"] = args.followers
    if args.rate is not None:
        env_changes["control_rate_hz"] = args.rate
    if env_changes:
        env = dataclasses.replace(env, **env_changes)
    if args.M is not None or args.k is not None:
        member = env.member_config
        member = dataclasses.replace(member, M=args.M or member.M, k=args.k or member.k)
        env = dataclasses.replace(env, member=member)
    r = config.randomization
    r_changes: dict = {}
    for flag, key in (
        ("per_range", "per_range"),
        ("burst_prob", "burst_prob"),
        ("latency_range", "latency_s_range"),
        ("gps_noise_range", "gps_noise_m_range"),
        ("scenarios", "scenarios"),
        ("vehicles", "vehicles"),
    ):
        if getattr(args, flag) is not None:
            r_changes[key] = (
                tuple(getattr(args, flag))
                if isinstance(getattr(args, flag), list)
                else getattr(args, flag)
            )
    if r_changes:
        r = dataclasses.replace(r, **r_changes)
    ppo, top = _switch_kind(config, env, top)
    return dataclasses.replace(config, env=env, randomization=r, ppo=ppo, **top)


def _switch_kind(
    config: TrainConfig, env: EnvSpec, top: dict[str, Any]
) -> tuple[PPOConfig, dict[str, Any]]:
    """``config``'s PPO settings and the top-level changes ``top`` for ``env``: where
    ``env`` is of the other kind (residual or from scratch) than ``config.env``, the run
    size and PPO settings that hold the other kind's defaults take this kind's
    (``config.run_defaults``; values a config chose, and flags given, stay)."""
    ppo = config.ppo
    residual = bool(env.base_policy)
    if residual == bool(config.env.base_policy):
        return ppo, top
    if ppo.use_sde == residual:  # the other kind's exploration (gSDE from scratch)
        ppo = dataclasses.replace(ppo, use_sde=None)
    (old_top, old_ppo), (new_top, new_ppo) = run_defaults(not residual), run_defaults(residual)
    run = {k: v for k, v in new_top.items() if getattr(config, k) == old_top[k]}
    ppo_changes = {k: v for k, v in new_ppo.items() if getattr(ppo, k) == old_ppo[k]}
    return dataclasses.replace(ppo, **ppo_changes), {**run, **top}


def _kind_defaults(env: EnvSpec, residual: bool) -> dict[str, Any]:
    """Changes that give ``env`` the defaults of residual (or absolute) actions where it
    holds the defaults of the other kind (values a config chose stay)."""
    if residual == bool(env.base_policy):
        return {}
    changes: dict[str, Any] = {}
    old = RESIDUAL_ACTION_BOUNDS if env.base_policy else ABSOLUTE_ACTION_BOUNDS
    if env.bounds == old:
        changes.update(action_low=None, action_high=None)
    if env.emergency_stop == bool(env.base_policy):
        changes["emergency_stop"] = None
    if env.reward == (TRAIN_REWARD if env.base_policy else SCRATCH_REWARD):
        changes["reward"] = None
    return changes


def train_command(args: argparse.Namespace) -> int:
    """``openconvoy train``: one run in this process, or several (``--seeds``, repeated
    ``--config``) as tasks of the executor (``openconvoy.train.multirun``)."""
    from openconvoy.train.train import train

    if args.seeds or len(args.config or ()) > 1 or args.executor == "ray":
        return _train_many(args)
    config = train_config_from_args(args)
    print(
        f"training {config.algo} for {config.total_steps} agent steps on {config.n_envs} envs x "
        f"{config.env.n_followers} followers"
        + (f", residual on {config.env.base_policy}" if config.env.base_policy else "")
        + f" -> {args.out}",
        file=sys.stderr,
    )
    if config.vec_env != "supersuit" and sys.stderr.isatty():  # a person waiting
        _say_compile()
    result = train(config, args.out, progress_bar=not args.no_progress, overwrite=args.overwrite)
    if result.validation is not None and result.base_validation is not None:
        from openconvoy.train.validate import comparison_lines

        for line in comparison_lines(result.validation, result.base_validation):
            print(line)
    print(
        f"{result.policy_path}  ({result.steps} steps in {result.wall_s:.0f} s, {result.steps_per_s:.0f} steps/s)"
    )
    return 0


def _say_compile() -> None:
    """The batched simulator's first compile, said before the wait it causes."""
    try:
        from openconvoy.envs.vector.jit import first_compile_note
    except ImportError:  # no numba: training falls back to SuperSuit
        return
    note = first_compile_note()
    if note is not None:
        print(note, file=sys.stderr)


def _train_many(args: argparse.Namespace) -> int:
    from openconvoy.experiments.executor import (
        ExecutorConfig,
        TasksFailed,
        make_executor,
        with_flags,
    )
    from openconvoy.train.multirun import plan, train_many

    if args.seed is not None and args.seeds:
        raise ConfigError("give --seed or --seeds, not both")
    if args.seeds and len(set(args.seeds)) != len(args.seeds):
        raise ConfigError(f"--seeds repeat: {' '.join(map(str, args.seeds))}")
    paths = args.config or [None]
    configs = [(_stem(p) if p else "default", train_config_from_args(args, p)) for p in paths]
    runs = plan(configs, args.seeds)
    executor = make_executor(with_flags(ExecutorConfig(), args.executor, args.address, args.jobs))
    print(
        f"training {len(runs)} runs on the {executor.kind} executor ({executor.slots} at once) -> {args.out}",
        file=sys.stderr,
    )
    try:
        summary = train_many(
            runs, args.out, executor, progress=not args.no_progress, overwrite=args.overwrite
        )
    except TasksFailed as exc:
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 1
    for entry in summary:
        print(
            f"{Path(args.out) / entry['policy']}  ({entry['steps']} steps in {entry['wall_s']:.0f} s on {entry['ran_on']})"
        )
    return 0


def tune_command(args: argparse.Namespace) -> int:
    """``openconvoy tune``; exit status 1 when trials failed (the study keeps the others)."""
    from openconvoy.experiments.executor import ExecutorConfig, TasksFailed, with_flags
    from openconvoy.train.tune import TuneConfig, tune, write_tuned

    if not args.out.endswith(".toml"):
        raise ConfigError(f"{args.out}: the tuned policy is a .toml file")
    if args.study_name is not None and args.storage is None:
        raise ConfigError("--study-name needs --storage (an in-memory study cannot be resumed)")
    config = TuneConfig(
        base=args.policy,
        trials=args.trials,
        pers=tuple(args.per),
        seeds=tuple(args.seeds),
        scenario=args.scenario,
        duration_s=args.duration,
        faults=tuple(args.fault or ()),
        auth=args.auth or "required",
        params=tuple(args.params or ()),
        seed=args.seed,
        name=_stem(args.out),
    )
    # Trials run one at a time in this process unless an executor or --jobs is asked for.
    jobs = args.jobs if args.jobs is not None else (None if args.executor == "ray" else 1)
    executor = with_flags(ExecutorConfig(), args.executor, args.address, jobs, args.batched)
    try:
        result = tune(
            config,
            progress_bar=not args.no_progress,
            executor=executor,
            study_name=args.study_name,
            storage=args.storage,
        )
    except TasksFailed as exc:
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 1
    path = write_tuned(result, args.out)
    values = ", ".join(f"{k} = {v:.4g}" for k, v in result.best_params.items())
    print(
        f"{path}: objective {result.best_value:.4f} (base {result.base_value:.4f}); {values}; "
        f"{len(result.history)} trials in study {result.study_name!r}, {result.evaluated} run now"
    )
    if result.failures:
        print(f"openconvoy: error: {len(result.failures)} trials failed:", file=sys.stderr)
        for f in result.failures:
            print(f"  {f.line()}", file=sys.stderr)
        return 1
    return 0


def export_command(args: argparse.Namespace) -> int:
    from openconvoy.policies.learned import load_learned, load_sb3_predict
    from openconvoy.train.export import (
        export_policy,
        max_action_difference,
        resolve_policy_zip,
        sample_observations,
    )

    if sys.stderr.isatty():  # progress for a person waiting; a script's stderr stays errors only
        print(
            f"exporting {resolve_policy_zip(args.run)} to {args.out}, then checking it against "
            "SB3's predict on 400 simulated observations (loads torch: ~10 s)",
            file=sys.stderr,
        )
    path = export_policy(args.run, args.out)
    trained = load_sb3_predict(resolve_policy_zip(args.run))  # torch: the reference
    exported = load_learned(path)
    obs = sample_observations(trained, n=400)
    diff = max_action_difference(trained, exported, obs)
    print(f"{path}: max |action difference| vs SB3 predict = {diff:.2e} on {len(obs)} observations")
    if diff > 1e-5:
        print(
            "openconvoy: error: the export does not reproduce the trained policy", file=sys.stderr
        )
        return 1
    return 0


def _stem(path: str) -> str:
    from pathlib import Path

    return Path(path).stem
