"""The ``openconvoy`` commands of learning: ``train``, ``tune``, ``export`` (their work is in
``commands``, imported when a command runs, so the parser needs no torch).
"""

from __future__ import annotations

import argparse

from openconvoy.core.args import DURATION, FRACTION, RATE_HZ, SEED, add_policy_arg, lazy_handler
from openconvoy.core.args import integer as _int
from openconvoy.core.args import number as _num
from openconvoy.experiments.cli import executor_args, fault_args


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train a follower policy (PPO/SAC, shared by all followers)",
        description="Train one policy for every follower with stable-baselines3 under "
        "domain randomization; write RUN_DIR/policy.zip (with its layout, member config "
        "and control rate), config.toml, checkpoints/ and TensorBoard logs (tb/). "
        "--config TRAIN.toml (a run's config.toml) describes it all; flags override it.",
    )
    _train_run_args(p)
    _train_env_args(p)
    _train_randomization_args(p)

    p.set_defaults(handler=lazy_handler("openconvoy.train.commands", "train_command"))


def _train_run_args(p: argparse.ArgumentParser) -> None:
    """What runs, where, and on what: config, algorithm, budget, seeds, executor."""
    p.add_argument(
        "--config",
        metavar="TRAIN.toml",
        action="append",
        help="training config file; repeat for one run per config (OUT/<stem>)",
    )
    p.add_argument("--algo", choices=("ppo", "sac"), help="algorithm (default ppo)")
    p.add_argument(
        "--steps", type=_int(1, 10**12), metavar="N", help="agent steps (default 600000)"
    )
    p.add_argument(
        "--out", default="runs/train", metavar="RUN_DIR", help="run directory (default runs/train)"
    )
    p.add_argument(
        "--budget",
        type=wall_clock,
        metavar="TIME",
        help="wall-clock budget of the run (900, 900s, 15m, 1h): learning stops in time "
        "to validate and write the run (default: none, or 14m with --base none)",
    )
    p.add_argument("--seed", type=SEED, help="seed (default 0)")
    p.add_argument(
        "--seeds",
        type=SEED,
        nargs="+",
        metavar="S",
        help="one run per seed (OUT/seed_S), run as tasks of --executor",
    )
    p.add_argument(
        "--jobs",
        type=_int(1, 4096),
        metavar="N",
        help="training runs at once (default: the cores available, or the cluster's CPUs)",
    )
    executor_args(p)
    p.add_argument(
        "--threads", type=_int(1, 1024), metavar="N", help="torch CPU threads (default 1)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace a policy already in RUN_DIR")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def wall_clock(text: str) -> float:
    """A duration ``N``, ``Ns``, ``Nm`` or ``Nh`` as seconds (``--budget``)."""
    units = {"s": 1.0, "m": 60.0, "h": 3600.0}
    t = text.strip().lower()
    scale = units.get(t[-1:], None)
    try:
        value = float(t[:-1] if scale else t) * (scale or 1.0)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a duration (e.g. 900, 900s, 15m, 1h)"
        ) from None
    if not 0.0 < value <= 7 * 86400.0:
        raise argparse.ArgumentTypeError(f"{text!r}: a duration in (0 s, 7 days]")
    return value


def _train_env_args(p: argparse.ArgumentParser) -> None:
    """The simulator, the convoys and the policy's inputs and outputs."""
    p.add_argument(
        "--vec-env",
        choices=("auto", "batched", "supersuit"),
        help="simulator: batched (all convoys in arrays), supersuit (one ConvoyEnv per "
        "convoy), auto (default: batched unless the configuration needs what only "
        "ConvoyEnv models)",
    )
    p.add_argument(
        "--envs", type=_int(1, 1024), metavar="N", help="convoys stepped together (default 32)"
    )
    p.add_argument(
        "--worlds",
        type=_int(1, 1024),
        metavar="N",
        help="batched: groups of convoys sharing a drawn world (default 2)",
    )
    p.add_argument(
        "--followers", type=_int(1, 1000), metavar="N", help="followers per environment (default 2)"
    )
    p.add_argument(
        "--base",
        metavar="SPEC",
        help="policy the network corrects (residual; default paper): a preset, policy "
        ".toml or plug-in (module:Name, file.py:Name), or 'none' for absolute actions",
    )
    add_policy_arg(p)
    p.add_argument(
        "--M",
        type=_int(1, 1000),
        help="observation: predecessors per observation (default: the base's)",
    )
    p.add_argument(
        "--k", type=_int(1, 1000), help="observation: states per vehicle (default: the base's)"
    )
    p.add_argument(
        "--rate", type=RATE_HZ, metavar="HZ", help="control rate (default: the base's, 20)"
    )


def _train_randomization_args(p: argparse.ArgumentParser) -> None:
    """What every episode redraws."""
    p.add_argument(
        "--per-range",
        type=FRACTION,
        nargs=2,
        metavar=("A", "B"),
        help="PER drawn in [A, B] (default 0 0.6)",
    )
    p.add_argument(
        "--burst-prob",
        type=FRACTION,
        metavar="P",
        help="chance of Gilbert-Elliott bursts per episode (default 0.3)",
    )
    p.add_argument(
        "--latency-range",
        type=_num(0.0, 60.0),
        nargs=2,
        metavar=("A", "B"),
        help="latency, seconds (default 0 0.05)",
    )
    p.add_argument(
        "--gps-noise-range",
        type=_num(0.0, 1000.0),
        nargs=2,
        metavar=("A", "B"),
        help="GPS noise std, metres (default 0 0; > 0 trains on SuperSuit's path)",
    )
    p.add_argument(
        "--scenarios", nargs="+", metavar="SPEC", help="scenarios drawn per episode (default paper)"
    )
    p.add_argument(
        "--vehicles",
        nargs="+",
        metavar="PRESET",
        help="vehicle presets or fitted preset .toml files drawn per vehicle (default 1/10 1/6)",
    )


def _add_tune(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "tune",
        help="tune a classical policy's parameters with Optuna",
        description="Search a classical policy's PD/PID gains, steering gain and spacing "
        "shape against the metrics over PERs and seeds; write the best as a policy "
        "TOML file (--policy accepts it) and OUT.json with the study's numbers.",
    )
    p.add_argument(
        "--policy",
        default="paper",
        metavar="BASE",
        help="preset, policy .toml, or plug-in (module:Name, file.py:Name) to start from",
    )
    add_policy_arg(p)
    p.add_argument("--trials", type=_int(1, 10**7), default=30, metavar="N")
    p.add_argument("--out", default="tuned.toml", metavar="FILE.toml")
    _tune_grid_args(p)
    p.add_argument(
        "--params", nargs="+", metavar="PATH", help="parameters (default: those the policy uses)"
    )
    p.add_argument("--seed", type=SEED, default=0, help="sampler seed")
    p.add_argument(
        "--storage",
        metavar="URL_OR_FILE",
        help="keep the study: an Optuna RDB URL (sqlite:///study.db, postgresql://...) "
        "or a journal file path; rerunning with it resumes the study",
    )
    p.add_argument(
        "--study-name", metavar="NAME", help="the study in --storage (default: OUT's stem)"
    )
    p.add_argument(
        "--jobs",
        type=_int(1, 4096),
        metavar="N",
        help="trials at once (default 1 locally, the cluster's CPUs on Ray)",
    )
    executor_args(p, batched=True)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p.set_defaults(handler=lazy_handler("openconvoy.train.commands", "tune_command"))


def _tune_grid_args(p: argparse.ArgumentParser) -> None:
    """The runs every trial is scored on: PERs x seeds of a scenario."""
    p.add_argument(
        "--per",
        type=FRACTION,
        nargs="+",
        default=[0.0, 0.3, 0.6],
        metavar="PER",
        help="PERs (default 0 0.3 0.6)",
    )
    p.add_argument(
        "--seeds",
        type=SEED,
        nargs="+",
        default=[1000, 1001],
        metavar="S",
        help="seeds (default 1000 1001, apart from the 0.. of reports)",
    )
    p.add_argument("--scenario", default="paper", metavar="SPEC")
    p.add_argument(
        "--duration", type=DURATION, metavar="S", help="run length (default: the scenario's)"
    )
    fault_args(p, "required", " in every run of every trial")


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a trained policy to a numpy-only .npz",
        description="Turn RUN_DIR/policy.zip (or a .zip) into a .npz that runs without "
        "torch (weights, observation normalization, action scaling, layout, member "
        "config, control rate), and check its actions against SB3's predict.",
    )
    p.add_argument("run", metavar="RUN_DIR", help="run directory or SB3 .zip")
    p.add_argument("--out", required=True, metavar="FILE.npz")

    p.set_defaults(handler=lazy_handler("openconvoy.train.commands", "export_command"))


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's commands to ``openconvoy``'s subparsers (handlers import lazily)."""
    _add_train(sub)
    _add_tune(sub)
    _add_export(sub)
