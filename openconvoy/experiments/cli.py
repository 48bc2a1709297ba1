"""The ``openconvoy`` commands of simulation and log analysis: ``sim``, ``report``, ``presets``,
``experiment per-sweep``, ``compare``, ``fit-plant`` (their work is in ``commands`` and
``fitplant``, imported when a command runs).
"""

from __future__ import annotations

import argparse

from openconvoy.core.args import DURATION, FRACTION, SECONDS_POS, SEED, add_policy_arg, lazy_handler
from openconvoy.core.args import integer as _int
from openconvoy.core.args import number as _num


def run_args(p: argparse.ArgumentParser, sweep: bool) -> None:
    """Arguments shared by ``sim`` and ``experiment per-sweep`` (None = not given)."""
    p.add_argument(
        "--scenario",
        default=None,
        metavar="SPEC",
        help="paper (default), track, emergency-braking, track-file:PATH, or with the "
        "traffic extra highway-cut-in, highway-merge, highway-slow-traffic, "
        "highway-lane-drop (optionally :key=value,...)",
    )
    p.add_argument(
        "--loss",
        choices=("bernoulli", "gilbert-elliott"),
        default=None,
        help="loss model of every link (default bernoulli"
        + ("" if sweep else "; or the convoy file's [channel] model")
        + ")",
    )
    p.add_argument(
        "--burst",
        type=SECONDS_POS,
        default=None,
        metavar="S",
        help="mean loss burst of gilbert-elliott, seconds (default 1)",
    )
    p.add_argument(
        "--duration",
        type=DURATION,
        default=None,
        metavar="S",
        help="run length (default: the scenario's)",
    )
    p.add_argument(
        "--followers", type=_int(1, 1000), default=None, metavar="N", help="number of followers"
    )
    p.add_argument(
        "--vehicle-preset",
        action="append",
        metavar="PRESET",
        help="vehicle preset name or .toml, repeated leader first (default: the scenario's)",
    )
    p.add_argument(
        "--ranging",
        action="store_true",
        help="give followers a ranging sensor (used by the staleness ladder's degraded mode)",
    )
    p.add_argument(
        "--ranging-range",
        type=_num(0.0, 10_000.0, lo_open=True),
        default=None if sweep else 20.0,
        metavar="M",
        help="that sensor's range in metres (default 20)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")


def executor_args(
    p: argparse.ArgumentParser, batched: bool = False, run_logs: bool = False
) -> None:
    """``--executor`` and ``--address`` (issue 15: sweeps, tune and train on Ray); with
    ``batched``, ``--batched/--no-batched`` (issue 14: sweeps and tune); with
    ``run_logs``, ``--no-run-logs`` (sweeps)."""
    if run_logs:
        p.add_argument(
            "--no-run-logs",
            action="store_true",
            help="write each run's metrics.json but not its log.csv (the summary is the same; "
            "writing the logs is much of a batched sweep's time)",
        )
    if batched:
        p.add_argument(
            "--batched",
            action=argparse.BooleanOptionalAction,
            default=None,
            help="run a policy's runs as a few batches of one VectorConvoyEnv each (default: "
            "where the numbers are the per-run path's to the bit, i.e. classical policies; "
            "--batched also learned ones; --no-batched one ConvoyEnv per run)",
        )
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default=None,
        help="where runs execute: local processes (default) or a Ray cluster (openconvoy[cluster])",
    )
    p.add_argument(
        "--address",
        default=None,
        metavar="ADDR",
        help="Ray cluster to use, HOST:PORT or auto (default: a private cluster of this machine)",
    )


def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="simulate one run: log, metrics and plots",
        description="Simulate a convoy and write DIR/log.csv, DIR/metrics.json, "
        "DIR/run.toml and plots (trajectories, gaps, speeds).",
    )
    p.add_argument(
        "--policy",
        default="paper",
        metavar="SPEC",
        help="preset (openconvoy presets; NAME+ladder), policy .toml, module:Name, "
        "file.py:Name, .zip or .npz",
    )
    add_policy_arg(p)
    p.add_argument(
        "--per",
        type=FRACTION,
        default=None,
        help="packet error rate 0..1 (default: the convoy file's [channel] per, else 0)",
    )
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument(
        "--out", default="runs/sim", metavar="DIR", help="output directory (default runs/sim)"
    )
    p.add_argument(
        "--convoy", metavar="CONVOY.toml", help="convoy file: scenario, vehicles, origin"
    )
    p.add_argument(
        "--bag",
        action="store_true",
        help="also record the run as a ROS 2 bag (MCAP) in DIR/bag (openconvoy[ros])",
    )
    _sim_world_args(p)
    run_args(p, sweep=False)

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "sim"))
    _add_report(sub)
    _add_presets(sub)


def _sim_world_args(p: argparse.ArgumentParser) -> None:
    """``sim``'s link delays, GPS noise, faults and authentication."""
    p.add_argument(
        "--latency",
        type=_num(0.0, 60.0),
        default=None,
        metavar="S",
        help="delivery delay, seconds, continuous (default: the convoy file's [channel], else 0)",
    )
    p.add_argument(
        "--jitter",
        type=_num(0.0, 60.0),
        default=None,
        metavar="S",
        help="uniform delay jitter, seconds (default: the convoy file's [channel], else 0)",
    )
    p.add_argument(
        "--gps-noise",
        type=_num(0.0, 1000.0),
        default=0.0,
        metavar="M",
        help="position noise std, metres",
    )
    fault_args(p, 'required; a convoy file\'s [v2v] auth = "off" turns it off')


def fault_args(p: argparse.ArgumentParser, auth_default: str, every: str = "") -> None:
    """``--fault`` (repeatable) and ``--auth`` (None = not given), for ``sim``, sweeps
    and ``tune``; ``every``: what the faults apply to, for the help."""
    p.add_argument(
        "--fault",
        action="append",
        metavar="KIND:VEHICLE@T_S",
        help=f"inject a fault{every} (repeatable): halt (brake to rest, keep broadcasting), "
        "silent (stop broadcasting, keep driving), dead (both) or forge (a keyless "
        "station claims to be the vehicle, 1 km ahead), e.g. dead:0@30, forge:0@10",
    )
    p.add_argument(
        "--auth",
        choices=("required", "off"),
        default=None,
        help=f"members authenticate messages, so forgeries are rejected (default {auth_default})",
    )


def _add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="recompute metrics from a log or run directory",
        description="Recompute the metrics from a log file or a directory of "
        "(per-vehicle) logs, print them and write metrics.json.",
    )
    p.add_argument("path", metavar="DIR_OR_LOG")
    p.add_argument(
        "--convoy",
        metavar="CONVOY.toml",
        help="vehicle lengths for logs without a length_m column (vehicle runs)",
    )
    p.add_argument(
        "--out", metavar="FILE", help="metrics file (default: metrics.json beside the log)"
    )
    p.add_argument("--plots", action="store_true", help="also draw trajectories, gaps and speeds")

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "report"))


def _add_presets(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("presets", help="list policy and vehicle presets")

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "presets"))


def _add_experiments(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("experiment", help="run experiments (per-sweep)")
    esub = p.add_subparsers(dest="experiment_command", metavar="EXPERIMENT", required=True)
    _add_per_sweep(esub)
    _add_leaderboard(esub)
    _add_compare(sub)


def _add_per_sweep(esub: argparse._SubParsersAction) -> None:
    p = esub.add_parser(
        "per-sweep",
        help="sweep packet error rates over seeds and policies",
        description="Run a scenario for each PER and seed (and policy), in parallel; "
        "write summary.json, summary.csv, every run's log and the paper's figures. "
        "--config EXPERIMENT.toml describes it all; flags given override it.",
    )
    p.add_argument(
        "--config",
        metavar="EXPERIMENT.toml",
        help="experiment file (a run directory's copy reruns it)",
    )
    p.add_argument(
        "--policy",
        action="append",
        metavar="SPEC",
        help="policy spec; repeat to draw several (e.g. --policy paper --policy paper+ladder)",
    )
    add_policy_arg(p)
    p.add_argument("--pers", metavar="LIST", help="comma-separated PERs (default 0,0.1,...,0.6)")
    p.add_argument(
        "--seeds",
        type=_int(1, 100_000),
        default=None,
        metavar="N",
        help="seeds 0..N-1 per PER (default 3)",
    )
    p.add_argument("--name", default=None, help="experiment name")
    p.add_argument("--out", default=None, metavar="DIR", help="the sweep's directory (required)")
    p.add_argument(
        "--resume",
        default=None,
        metavar="DIR",
        help="finish the interrupted sweep in DIR: run only the runs it lacks, then write "
        "its summary (the same as an uninterrupted sweep's); with --jobs/--executor only",
    )
    p.add_argument(
        "--jobs",
        type=_int(1, 4096),
        default=None,
        metavar="N",
        help="runs at once (default: the cores available, or the Ray cluster's CPUs)",
    )
    executor_args(p, batched=True, run_logs=True)
    run_args(p, sweep=True)
    fault_args(
        p,
        "the experiment file's auth, else required",
        " in every run, replacing the experiment file's faults",
    )

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "per_sweep"))


def _add_leaderboard(esub: argparse._SubParsersAction) -> None:
    p = esub.add_parser(
        "leaderboard",
        help="policies x scenarios x link conditions x seeds, as one table with 95 % intervals",
        description="Run every policy on every scenario under every link condition of "
        "--config LEADERBOARD.toml (one per-sweep per scenario and condition) and write "
        "leaderboard.csv, leaderboard.md and leaderboard.png: p95 platooning error, speed "
        "difference, min gap, collisions and string stability, each with its 95 %% interval "
        "over seeds. Rerun on the same --out (or --resume DIR) to finish an interrupted one.",
    )
    p.add_argument("--config", metavar="LEADERBOARD.toml", help="leaderboard file")
    p.add_argument("--out", default=None, metavar="DIR", help="the leaderboard's directory")
    p.add_argument(
        "--resume",
        default=None,
        metavar="DIR",
        help="finish the leaderboard in DIR (its own leaderboard.toml): finished cells are read",
    )
    p.add_argument(
        "--scenarios", metavar="LIST", help="comma-separated scenarios, replacing the file's"
    )
    p.add_argument(
        "--seeds",
        type=_int(1, 100_000),
        default=None,
        metavar="N",
        help="seeds 0..N-1 (replacing the file's)",
    )
    p.add_argument(
        "--jobs",
        type=_int(1, 4096),
        default=None,
        metavar="N",
        help="runs at once (default: the cores available, or the Ray cluster's CPUs)",
    )
    executor_args(p, batched=True, run_logs=True)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true", help="skip the plot")

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "leaderboard"))


def _add_compare(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="two runs or sweeps side by side, with differences",
        description="Metrics of two runs (log files or run directories, sim or "
        "vehicle) or two sweeps (directories with summary.json) side by side; B - A.",
    )
    p.add_argument("a", metavar="A")
    p.add_argument("b", metavar="B")
    p.add_argument(
        "--convoy", metavar="CONVOY.toml", help="vehicle lengths for logs without length_m"
    )
    p.add_argument("--out", metavar="FILE.json", help="also write the comparison as JSON")

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.commands", "compare"))


def _add_fit_plant(sub: argparse._SubParsersAction) -> None:
    """``fit-plant``: log analysis (``experiments.fitplant``)."""
    p = sub.add_parser(
        "fit-plant",
        help="fit a vehicle preset (lag, accel limits, turn rate, delay) from a vehicle run's logs",
        description="Replays the logged commands through the simulator's plant model and fits "
        "speed lag, acceleration/deceleration limits, turn-rate limit, heading lag and "
        "actuation delay; writes a preset TOML that sim and experiment accept.",
    )
    p.add_argument(
        "log",
        metavar="LOG_DIR",
        nargs="+",
        help="a run directory of per-vehicle logs, or one log; with --model pi also "
        "MAVLink recordings (.jsonl.gz, as in shared/sitl), several allowed",
    )
    p.add_argument(
        "--model",
        choices=("lag", "pi"),
        default="lag",
        help="lag: first-order speed lag (default); pi: the autopilot's PI speed loop "
        "with its delay, accel ramp and static friction, and its heading loop",
    )
    p.add_argument(
        "--source",
        choices=("telemetry", "truth"),
        default="telemetry",
        help="recordings: fit GLOBAL_POSITION_INT/ATTITUDE (default) or PX4 SIH's "
        "true state (HIL_STATE_QUATERNION)",
    )
    p.add_argument("--out", metavar="PRESET.toml", help="output file (default NAME.toml)")
    p.add_argument("--name", default="fitted", help="preset name (default fitted)")
    p.add_argument(
        "--base",
        default=None,
        help="preset giving what logs cannot show: size, steering, speed cap (default 1/10; "
        "with --convoy the shipped preset of the run's autopilot)",
    )
    p.add_argument(
        "--convoy",
        metavar="CONVOY.toml",
        help="calibrate a whole vehicle run (LOG_DIR, deploy logs): fit every vehicle and "
        "the V2V channel and write --out-convoy (docs/calibration.md)",
    )
    p.add_argument(
        "--out-convoy",
        metavar="FITTED.toml",
        help="with --convoy: the convoy file to write (presets beside it); then "
        "sim --convoy FITTED.toml and compare LOG_DIR SIM_DIR",
    )
    p.add_argument(
        "--vehicle-id", type=_int(0, 254), help="which vehicle, when the logs hold several"
    )
    p.add_argument(
        "--cmd-timing",
        choices=("after-state", "before-state"),
        default="after-state",
        help="a row's command was computed from its state (OpenConvoy's sim and "
        "vehicle logs) or led to it (some other tools' logs)",
    )

    p.set_defaults(handler=lazy_handler("openconvoy.experiments.fitplant", "run_fit_plant_cli"))


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's commands to ``openconvoy``'s subparsers (handlers import lazily)."""
    _add_sim(sub)
    _add_experiments(sub)
    _add_fit_plant(sub)
