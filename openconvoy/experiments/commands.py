"""The work behind ``openconvoy sim``, ``report``, ``presets``, ``experiment per-sweep`` and
``compare`` (``openconvoy.cli`` declares their arguments and calls these lazily).

Bad arguments raise ``ValueError`` with one line naming the problem; the CLI prints it as
``openconvoy: error: ...``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from openconvoy.core import metrics as mt
from openconvoy.core.errors import ConfigError, OutputPathError


def _lengths_from_convoy(path: str | None) -> dict[int, float] | None:
    if not path:
        return None
    from openconvoy.convoy import load_convoy
    from openconvoy.envs.vehicles import vehicle_preset

    convoy = load_convoy(path)
    return {i: vehicle_preset(v).length_m for i, v in enumerate(convoy.vehicles)}


def _check_per(per: float) -> None:
    if not 0.0 <= per <= 1.0:
        raise ConfigError(f"--per must be in [0, 1], got {per}")


def format_metrics(metrics: dict[str, Any]) -> str:
    """The metrics as aligned ``key  value`` lines, per-follower p95 errors after them."""
    lines = []
    for k in mt.METRIC_KEYS + tuple(k for k in mt.TRAFFIC_METRIC_KEYS if k in metrics):
        v = metrics[k]
        lines.append(
            f"{k:<28}{' ' * (len(k) >= 28)}{'nan' if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, '.4g')}"
        )
    for f, values in metrics.get("per_follower", {}).items():
        v = values["p95_platooning_error_m"]
        lines.append(
            f"  follower {f} p95 error (m)  {format(v, '.4g') if v is not None else 'nan'}"
        )
    return "\n".join(lines)


# --- sim ---------------------------------------------------------------------------------


def run_config_from_args(args: argparse.Namespace) -> Any:
    """The RunConfig that ``openconvoy sim``'s arguments describe."""
    from openconvoy.convoy import ChannelConfig
    from openconvoy.experiments.runs import ConvoySection, LossSection, RunConfig

    scenario, vehicles, origin = args.scenario, tuple(args.vehicle_preset or ()), None
    plants: tuple[str, ...] = ()
    auth = getattr(args, "auth", None)
    channel = ChannelConfig()
    if args.convoy:
        from openconvoy.convoy import load_convoy

        convoy = load_convoy(args.convoy)
        scenario = scenario or convoy.scenario
        plants = () if vehicles else convoy.plants
        vehicles = vehicles or convoy.vehicles
        origin = convoy.origin
        auth = auth or ("off" if convoy.v2v.auth == "off" else None)
        channel = convoy.channel
    # Flags given on the command line win over the convoy file's [channel].
    per = channel.per if args.per is None else args.per
    _check_per(per)
    latency = channel.latency_s if args.latency is None else args.latency
    jitter = channel.jitter_s if args.jitter is None else args.jitter
    samples = channel.latency_samples_s if args.jitter is None else ()
    model = channel.model if args.loss is None else args.loss
    if args.burst is not None and model != "gilbert-elliott":
        raise ConfigError("--burst applies to --loss gilbert-elliott")
    burst = args.burst if args.burst is not None else channel.mean_burst_s
    return RunConfig(
        scenario=scenario or "paper",
        policy=args.policy,
        per=per,
        seed=args.seed,
        duration_s=args.duration,
        convoy=ConvoySection(
            vehicles=vehicles,
            n_followers=args.followers,
            ranging=args.ranging,
            ranging_max_range_m=args.ranging_range,
            gps_noise_m=args.gps_noise,
            plants=plants,
        ),
        loss=LossSection(
            model=model,
            mean_burst_s=burst,
            latency_s=latency,
            jitter_s=jitter,
            latency_samples_s=samples,
            stamp_error_s=channel.stamp_error_s,
            stamp_drift=channel.stamp_drift,
            link_latency_s=channel.link_latency_s if args.jitter is None else (),
            staleness_s=channel.staleness_s,
            # --per draws losses at that rate: the run's recorded ones are not replayed.
            lost_s=channel.lost_s if args.per is None else (),
            lost_window_s=channel.lost_window_s,
        ),
        origin=origin,
        faults=tuple(getattr(args, "fault", None) or ()),
        auth=auth or "required",
    )


def plots_wanted(no_plots: bool) -> bool:
    """Whether to draw figures: not with ``--no-plots``, and not without matplotlib (the
    ``plots`` extra), which a minimal install lacks: then one note on stderr and the run's
    other files as usual."""
    if no_plots:
        return False
    try:
        import matplotlib  # noqa: F401  (the figures import it again)
    except ModuleNotFoundError:
        print(
            "openconvoy: note: no plots, matplotlib is not installed "
            "(pip install 'openconvoy[plots]'; --no-plots skips them)",
            file=sys.stderr,
        )
        return False
    return True


def sim(args: argparse.Namespace) -> int:
    """``openconvoy sim``: one run; writes log.csv, metrics.json, run.toml and plots."""
    from openconvoy import __version__
    from openconvoy.core.config import dumps_toml
    from openconvoy.experiments.runs import build_env, run_sim
    from openconvoy.outputs import check_output_dir

    config = run_config_from_args(args)
    build_env(config)  # a bad policy, scenario or preset fails before anything is written
    out = check_output_dir(args.out, "--out")
    out.mkdir(parents=True, exist_ok=True)
    bag = None
    if getattr(args, "bag", False):
        bag = out / "bag"
        if (bag / "metadata.yaml").is_file():
            import shutil

            shutil.rmtree(bag)  # a previous run's bag: overwritten, like log.csv
        elif bag.exists():
            raise OutputPathError(f"--bag: {bag} exists and is not a ROS 2 bag; move it away")
    result = run_sim(config, out, progress=not args.quiet, bag=bag)
    (out / "run.toml").write_text(
        f"# openconvoy {__version__}\n" + dumps_toml({"run": config.to_dict()}), encoding="utf-8"
    )
    written = ["log.csv", "metrics.json", "run.toml"] + (["events.json"] if result.events else [])
    written += ["bag/"] if bag is not None else []
    if plots_wanted(args.no_plots):
        from openconvoy.experiments.figures import run_figures

        label = f"({config.scenario}, {config.policy}, PER {config.per:g}, seed {config.seed})"
        written += [p.name for p in run_figures(result.log, out, label)]
    print(format_metrics(result.metrics))
    print(f"wrote {', '.join(written)} to {out}")
    return 0


# --- report ------------------------------------------------------------------------------


MOVED_SPEED_MPS = 0.05
MOVED_DISTANCE_M = 0.5


def standstill_warning(log: dict[str, Any]) -> str:
    """One warning line when no vehicle in the log moved (every |speed| below
    ``MOVED_SPEED_MPS`` and every vehicle within ``MOVED_DISTANCE_M`` of where it began),
    else "": metrics of a convoy that never drove (armed in MANUAL, say) look perfect."""
    import numpy as np

    speed = np.abs(np.asarray(log["speed_mps"], dtype=float))
    ids = np.asarray(log["vehicle_id"])
    x, y = np.asarray(log["x_m"], dtype=float), np.asarray(log["y_m"], dtype=float)
    moved = 0.0
    for v in np.unique(ids):
        sel = (ids == v) & np.isfinite(x) & np.isfinite(y)
        if sel.any():
            xs, ys = x[sel], y[sel]
            moved = max(moved, float(np.max(np.hypot(xs - xs[0], ys - ys[0]))))
    fastest = float(np.nanmax(speed)) if np.isfinite(speed).any() else 0.0
    if fastest >= MOVED_SPEED_MPS or moved >= MOVED_DISTANCE_M:
        return ""
    return (
        f"warning: no vehicle moved (fastest {fastest:.2f} m/s, farthest {moved:.2f} m from "
        "its start): these metrics describe a convoy that stood still"
    )


def report(args: argparse.Namespace) -> int:
    """``openconvoy report``: recompute metrics from a log file or a run directory."""
    from openconvoy.experiments.runs import write_json
    from openconvoy.logs import read_log_counted
    from openconvoy.outputs import check_output_file

    path = Path(args.path)
    if args.out:
        check_output_file(args.out, "--out")
    log, left_out = read_log_counted(path)
    if left_out:
        per = ", ".join(f"vehicle {v}: {n}" for v, n in sorted(left_out.items()))
        print(
            f"note: left out {sum(left_out.values())} rows written without telemetry "
            f"(the autopilot link was lost; {per})"
        )
    lengths = _lengths_from_convoy(args.convoy)
    if lengths is None and "length_m" not in log:
        print(
            "note: the log has no vehicle lengths; pass --convoy to count collisions "
            "against half lengths (now: centre distance < 0)"
        )
    metrics = mt.compute_metrics(log, lengths)
    if mt.has_traffic_columns(log):
        metrics.update(mt.traffic_metrics(log, lengths or mt.lengths_from_log(log)))
    print(format_metrics(metrics))
    warning = standstill_warning(log)
    if warning:
        print(warning, file=sys.stderr)
    from openconvoy.bag import is_bag

    # metrics.json beside a log file, in a run directory, beside a bag (never inside it)
    base = (path if path.is_dir() else path.parent).parent if is_bag(path) else path
    out = Path(args.out) if args.out else (base if base.is_dir() else base.parent) / "metrics.json"
    write_json(out, metrics)
    written = [str(out)]
    if args.plots:
        from openconvoy.experiments.figures import run_figures

        written += [str(p) for p in run_figures(log, out.parent)]
    print(f"wrote {', '.join(written)}")
    return 0


# --- presets -----------------------------------------------------------------------------


def _start_threshold(p) -> float:
    """The setpoint (m/s) below which a preset with static friction does not start from
    rest: its first drive command is (ff + kp) x setpoint for the ``pi`` loop."""
    return p.breakaway_mps / (p.speed_ff + p.speed_kp) if p.speed_loop == "pi" else p.breakaway_mps


def presets(args: argparse.Namespace) -> int:
    """``openconvoy presets``: policy presets, one line each, then vehicle presets."""
    from openconvoy.envs.vehicles import VEHICLE_PRESETS
    from openconvoy.policies.presets import PRESETS

    width = max(len(n) for n in PRESETS)
    print("policy presets (--policy NAME, NAME+ladder for the staleness ladder):")
    for name, cfg in PRESETS.items():
        m = cfg.member
        parts = f"{m.topology}, {m.trigger.kind}, {m.spacing.kind}, {'mpc' if cfg.mpc is not None else cfg.speed.kind} + {cfg.heading.kind}"
        print(f"  {name:<{width}}  [{parts}] {cfg.description}")
    from openconvoy.core.plugins import ENTRY_POINT_GROUPS, entry_points

    for kind, group in ENTRY_POINT_GROUPS.items():
        found = entry_points(kind)
        if found:
            how = "--policy NAME" if kind == "policy" else 'kind = "NAME" in a policy TOML'
            print(f"installed {kind} plug-ins ({group} entry points; {how}):")
            for name, ep in sorted(found.items()):
                print(f"  {name:<{width}}  {ep.value}")
    print("vehicle presets (--vehicle-preset NAME or a preset .toml):")
    for name, p in VEHICLE_PRESETS.items():
        print(
            f"  {name:<{width}}  length {p.length_m:g} m, accel {p.accel_max_mps2:g} / decel "
            f"{p.decel_max_mps2:g} m/s², turn rate {math.degrees(p.turn_rate_max_radps):.0f}°/s, "
            f"delay {p.actuation_delay_s:g} s, max {p.max_speed_mps:g} m/s"
            + (", the autopilot's PI speed loop" if p.speed_loop == "pi" else "")
            + (
                f", no start from rest below {_start_threshold(p):.2g} m/s"
                if p.breakaway_mps
                else ""
            )
            + (", ranging sensor" if p.ranging else "")
        )
    return 0


# --- experiment per-sweep ----------------------------------------------------------------


def _floats(text: str) -> tuple[float, ...]:
    try:
        pers = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        pers = ()
    if not pers or not all(0.0 <= p <= 1.0 for p in pers):
        raise ConfigError(
            f"--pers: expected comma-separated packet error rates in [0, 1], got {text!r}"
        )
    return pers


def experiment_from_args(args: argparse.Namespace) -> Any:
    """The ExperimentConfig of ``experiment per-sweep``: ``--config`` (if given) with any
    explicitly given flags on top, else the defaults with the flags."""
    from openconvoy.experiments.sweep import ExperimentConfig, with_overrides

    config = ExperimentConfig.from_toml(args.config) if args.config else ExperimentConfig()
    changes: dict[str, Any] = {}
    if args.name:
        changes["name"] = args.name
    if args.scenario:
        changes["scenario"] = args.scenario
    if args.policy:
        changes["policies"] = tuple(args.policy)
    if args.pers is not None:
        changes["pers"] = _floats(args.pers)
    if args.seeds is not None:
        if args.seeds < 1:
            raise ConfigError(f"--seeds must be at least 1, got {args.seeds}")
        changes["seeds"] = tuple(range(args.seeds))
    if args.duration is not None:
        changes["duration_s"] = args.duration
    if args.loss:
        changes["model"] = args.loss
    if args.burst is not None:
        changes["mean_burst_s"] = args.burst
    if args.followers is not None:
        changes["n_followers"] = args.followers
    if args.vehicle_preset:
        changes["vehicles"] = tuple(args.vehicle_preset)
    if args.ranging:
        changes["ranging"] = True
    if args.ranging_range is not None:
        changes["ranging_max_range_m"] = args.ranging_range
    if args.fault:
        changes["faults"] = tuple(args.fault)
    if args.auth is not None:
        changes["auth"] = args.auth
    config = with_overrides(config, **changes) if changes else config
    # Re-validate the result (dataclasses.replace runs __post_init__ too).
    return config


def per_sweep(args: argparse.Namespace) -> int:
    """``openconvoy experiment per-sweep``; exit status 1 when runs failed (the others
    are written)."""
    import sys

    from openconvoy.experiments.executor import TasksFailed, with_flags
    from openconvoy.experiments.sweep import SweepInterrupted, run_experiment

    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {args.jobs}")
    from openconvoy.outputs import check_output_dir

    if args.resume is not None:
        config, out = _resumed(args)
    else:
        if args.out is None:
            raise ConfigError("experiment per-sweep needs --out DIR (or --resume DIR)")
        config = experiment_from_args(args)
        out = check_output_dir(args.out, "--out", create=False)  # created once checked
    executor = with_flags(config.executor, args.executor, args.address, args.jobs, args.batched)
    figures = plots_wanted(args.no_plots)
    try:
        result = run_experiment(
            config,
            out,
            progress=not args.quiet,
            figures=figures,
            executor=executor,
            run_logs=not args.no_run_logs,
            resume=args.resume is not None,
        )
    except TasksFailed as exc:
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 1
    except SweepInterrupted as exc:
        print(f"openconvoy: {exc}", file=sys.stderr)
        return 130
    print(
        f"{'policy':<24}{'PER':>5}{'p95 err (m)':>13}{'dv (m/s)':>10}{'min gap (m)':>13}{'collisions':>12}{'delivery':>10}"
    )
    for r in result.rows:
        print(
            f"{r['policy']:<24}{r['per']:>5.2f}{r['p95_platooning_error_m']['mean']:>13.3f}"
            f"{r['mean_speed_difference_mps']['mean']:>10.3f}{r['min_gap_m']['mean']:>13.2f}"
            f"{r['collisions']['mean']:>12.2f}{r['delivery_ratio']['mean']:>10.3f}"
        )
    print(
        f"wrote summary.json, summary.csv, experiment.toml, {'figures, ' if figures else ''}"
        f"{len(result.runs)} run "
        f"{'logs' if not args.no_run_logs else 'metrics'} to {out}"
    )
    return 0


_RESUME_EXCLUSIVE = (
    "config", "policy", "pers", "seeds", "name", "out", "scenario", "loss", "burst", "duration",
    "followers", "vehicle_preset", "ranging", "ranging_range", "fault", "auth", "no_run_logs",
)  # fmt: skip


def _resumed(args: argparse.Namespace) -> tuple[Any, Path]:
    """``--resume DIR``: the sweep's own experiment file and directory; flags that would
    change the experiment are refused (a resumed sweep is the one that was started)."""
    from openconvoy.experiments.sweep import ExperimentConfig

    given = [n for n in _RESUME_EXCLUSIVE if getattr(args, n, None) not in (None, False)]
    if given:
        flag = "--" + given[0].replace("_", "-")
        raise ConfigError(f"--resume runs the sweep as it was started: {flag} cannot change it")
    out = Path(args.resume)
    if not (out / "experiment.toml").is_file():
        raise ConfigError(f"--resume: {out} holds no sweep (no experiment.toml)")
    return ExperimentConfig.from_toml(out / "experiment.toml"), out


# --- experiment leaderboard -------------------------------------------------------------


def leaderboard(args: argparse.Namespace) -> int:
    """``openconvoy experiment leaderboard``; exit status 1 when runs failed, 130 when
    interrupted (the finished runs are kept for ``--resume``)."""
    from openconvoy.experiments import leaderboard as lb
    from openconvoy.experiments.executor import TasksFailed, with_flags
    from openconvoy.experiments.sweep import SweepInterrupted
    from openconvoy.outputs import check_output_dir

    if args.resume is not None:
        if args.config or args.out or args.scenarios or args.seeds is not None:
            raise ConfigError(
                "--resume runs the leaderboard as it was started: no --config, "
                "--out, --scenarios or --seeds"
            )
        copy = Path(args.resume) / "leaderboard.toml"
        if not copy.is_file():
            raise ConfigError(f"--resume: {args.resume} holds no leaderboard (no leaderboard.toml)")
        config, out = lb.LeaderboardConfig.from_toml(copy), Path(args.resume)
    else:
        if not args.config or not args.out:
            raise ConfigError(
                "experiment leaderboard needs --config FILE and --out DIR (or --resume DIR)"
            )
        config = lb.LeaderboardConfig.from_toml(args.config)
        changes: dict[str, Any] = {}
        if args.scenarios:
            changes["scenarios"] = tuple(s.strip() for s in args.scenarios.split(",") if s.strip())
        if args.seeds is not None:
            changes["seeds"] = tuple(range(args.seeds))
        config = lb.with_overrides(config, **changes) if changes else config
        out = check_output_dir(args.out, "--out")
    executor = with_flags(config.executor, args.executor, args.address, args.jobs, args.batched)
    try:
        rows = lb.run_leaderboard(
            config,
            out,
            progress=not args.quiet,
            figures=plots_wanted(args.no_plots),
            executor=executor,
            run_logs=not args.no_run_logs,
        )
    except TasksFailed as exc:
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 1
    except SweepInterrupted as exc:
        print(f"openconvoy: {exc}", file=sys.stderr)
        return 130
    print(lb.table_markdown(rows), end="")
    print(f"wrote leaderboard.csv, leaderboard.md, leaderboard.json to {out}")
    return 0


# --- compare -----------------------------------------------------------------------------


def compare(args: argparse.Namespace) -> int:
    """``openconvoy compare A B``."""
    from openconvoy.experiments import compare as cmp
    from openconvoy.experiments.runs import write_json
    from openconvoy.outputs import check_output_file

    if args.out:
        check_output_file(args.out, "--out")
    lengths = _lengths_from_convoy(args.convoy)
    result = cmp.compare(*cmp.load_pair(args.a, args.b, lengths))
    print(cmp.format_comparison(result))
    if args.out:
        write_json(args.out, result)
        print(f"wrote {args.out}")
    return 0
