"""``fit-plant``: fit a vehicle preset's inner-loop response from a vehicle run's log.

The model is the simulator's plant (``envs.plant``): after an actuation delay, speed follows
its setpoint with a first-order lag clipped by the acceleration/deceleration limits, and
heading follows with a lag clipped by the turn-rate limit (and the bicycle's curvature at
the measured speed). The log gives, per control tick, the measured speed and heading and
the commands sent (``cmd_speed_mps``; heading setpoint = logged heading +
``cmd_heading_change_rad``). Each candidate parameter set replays the commands (held
between ticks, on a fine time grid) and is scored by the squared error to the measured
speed, then heading. The search is a grid refined around the best point, vectorized over
candidates with numpy (no optimizer dependency).

The fitted delay is the delay from a command to its first effect on the measurement. On a
vehicle that includes the link's latency; when the log has a ``telemetry_age_s`` column (the
age of the state each row was computed from), measurements are placed at ``t_s - age`` and
the telemetry's staleness drops out of the delay.
Parameters the log cannot show (size, steering lock, speed cap) come from a base preset.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from openconvoy.core.errors import ConfigError, InputFileError
from openconvoy.envs.vehicles import VehiclePreset, preset_to_toml, vehicle_preset
from openconvoy.logs import read_log

_FINE_DT_S = 0.01  # replay grid; 1 cm/s-level resolution of the delay search


@dataclass(frozen=True)
class PlantFit:
    """Result of a fit.

    Attributes:
        preset: the base preset with the fitted response parameters.
        speed_rms_mps: RMS error of the replayed speed against the log.
        heading_rms_rad: RMS error of the replayed heading against the log.
        samples: log rows used.
        limits_hit: per limit (``accel_max_mps2``, ``decel_max_mps2``,
            ``turn_rate_max_radps``), whether the run ever pushed against it; a limit
            never reached is not measured (the preset keeps the base value or the lower
            bound the run shows, whichever is higher).
        cmd_timing: the log's command timing used (see ``CmdTiming``).
    """

    preset: VehiclePreset
    speed_rms_mps: float
    heading_rms_rad: float
    samples: int
    limits_hit: dict[str, bool]
    cmd_timing: str


def _select_vehicle(log: dict[str, np.ndarray], vehicle_id: int | None) -> np.ndarray:
    ids = np.unique(log["vehicle_id"])
    if vehicle_id is None:
        if len(ids) != 1:
            raise InputFileError(
                f"the log holds vehicles {', '.join(map(str, ids))}: choose one with --vehicle-id"
            )
        vehicle_id = int(ids[0])
    mask = log["vehicle_id"] == vehicle_id
    if not mask.any():
        raise InputFileError(
            f"no rows for vehicle {vehicle_id} in the log (has {', '.join(map(str, ids))})"
        )
    return mask


def _resample(
    t: np.ndarray, t_cmd: np.ndarray, *series: np.ndarray
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Fine time grid over the measurement times ``t``; commands (sent at ``t_cmd``) held
    (zero-order) until the next one. Returns (grid, held series, grid index of each row)."""
    n = int(round((t[-1] - t[0]) / _FINE_DT_S)) + 1
    grid = t[0] + _FINE_DT_S * np.arange(n)
    rows_on_grid = np.clip(np.round((t - t[0]) / _FINE_DT_S).astype(int), 0, n - 1)
    cmd_on_grid = np.round((t_cmd - t[0]) / _FINE_DT_S).astype(int)
    # Command k holds from its own grid point on (indices, not float comparisons).
    row_of = np.clip(
        np.searchsorted(cmd_on_grid, np.arange(n), side="right") - 1, 0, len(t_cmd) - 1
    )
    return grid, [x[row_of] for x in series], rows_on_grid


def _row_targets(n: int, rows: np.ndarray, measured: np.ndarray) -> list[list[float]]:
    """For each fine step, the measured values of the log rows that fall on it."""
    at: list[list[float]] = [[] for _ in range(n)]
    for r, m in zip(rows, measured):
        at[r].append(float(m))
    return at


def _replay_speed(
    v0: float,
    cmd: np.ndarray,
    delay: np.ndarray,
    tau: np.ndarray,
    acc: np.ndarray,
    dec: np.ndarray,
    at: list[list[float]],
) -> np.ndarray:
    """Mean squared speed error at the log rows for each candidate (vectorized)."""
    steps = np.round(delay / _FINE_DT_S).astype(int)
    v = np.full(len(tau), v0)
    sse = np.zeros(len(tau))
    count = 0
    for i in range(len(cmd)):
        for m in at[i]:
            sse += (v - m) ** 2
            count += 1
        # Before the first logged command has come through, the vehicle holds its speed.
        err = np.where(i >= steps, cmd[np.maximum(i - steps, 0)], v0) - v
        dv = np.clip(err / tau, -dec, acc) * _FINE_DT_S
        v = v + np.where(np.abs(dv) > np.abs(err), err, dv)  # never overshoot in one step
    return sse / max(count, 1)


def _replay_heading(
    h0: float,
    cmd: np.ndarray,
    speed: np.ndarray,
    kappa: float,
    delay_steps: int,
    rate_max: np.ndarray,
    tau: np.ndarray,
    at: list[list[float]],
) -> np.ndarray:
    """Mean squared (wrapped) heading error at the log rows for each candidate."""
    h = np.full(len(tau), h0)
    tau = np.maximum(tau, _FINE_DT_S)
    sse = np.zeros(len(tau))
    count = 0
    for i in range(len(cmd)):
        for m in at[i]:
            sse += ((h - m + math.pi) % (2 * math.pi) - math.pi) ** 2
            count += 1
        target = cmd[i - delay_steps] if i >= delay_steps else h0
        err = (target - h + math.pi) % (2 * math.pi) - math.pi
        cap = np.minimum(rate_max, abs(speed[i]) * kappa)
        h = h + np.clip(err / tau, -cap, cap) * _FINE_DT_S
    return sse / max(count, 1)


def _refine(
    score,
    bounds: list[tuple[float, float]],
    log_scale: list[bool],
    points: list[int],
    step: list[float | None],
    rounds: int = 8,
    shrink: float = 0.5,
) -> tuple[np.ndarray, float]:
    """Grid search refined around the best point; ``score`` maps a (k, d) array of
    candidates to k costs. An axis with a ``step`` is discrete (the delay, in replay
    steps): after the first round it spans the best value +- 4 steps, so the other axes'
    refinement cannot lock the delay into a neighbouring basin."""
    lo = np.array([math.log(b[0]) if ls else b[0] for b, ls in zip(bounds, log_scale)])
    hi = np.array([math.log(b[1]) if ls else b[1] for b, ls in zip(bounds, log_scale)])
    full_lo, full_hi = lo.copy(), hi.copy()
    best, best_cost = None, math.inf
    for r in range(rounds):
        axes = []
        for i, (a, b, p) in enumerate(zip(lo, hi, points)):
            step_i = step[i]
            if step_i is not None and best is not None:
                values = best[i] + step_i * np.arange(-4, 5)
                axes.append(values[(values >= full_lo[i] - 1e-12) & (values <= full_hi[i] + 1e-12)])
            else:
                axes.append(np.linspace(a, b, p if r == 0 else max(5, p // 2 + 1)))
        mesh = np.stack([m.ravel() for m in np.meshgrid(*axes, indexing="ij")], axis=1)
        cand = np.where(log_scale, np.exp(mesh), mesh)
        costs = score(cand)
        k = int(np.argmin(costs))
        if costs[k] < best_cost:
            best, best_cost = mesh[k], float(costs[k])
        width = (hi - lo) * shrink
        lo = np.maximum(full_lo, best - width / 2)
        hi = np.minimum(full_hi, best + width / 2)
    assert best is not None
    return np.where(log_scale, np.exp(best), best), best_cost


CmdTiming = Literal["after-state", "before-state"]
"""How a log row's command relates to its state. ``after-state`` (OpenConvoy's logs, sim and
vehicle alike): the command was computed from the row's state and sent at ``t_s``.
``before-state`` (some other tools' logs): the row's command was applied during the tick
that led to the row's state, i.e. sent at the previous row, relative to the previous row's
heading. The two differ by one tick in the fitted delay, and a log alone cannot tell them
apart (shifting every command by a tick is the same as a tick more delay)."""


@dataclass
class _Data:
    t: np.ndarray  # measurement times (rows)
    speed: np.ndarray
    heading: np.ndarray
    age: np.ndarray
    t_cmd: np.ndarray  # command times
    cmd_v: np.ndarray
    cmd_h: np.ndarray  # absolute heading setpoints


_Columns = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""A vehicle's log columns: t, speed, heading, commanded speed and heading change, age."""


def _load(log_path: str | Path, vehicle_id: int | None) -> _Columns:
    log = read_log(log_path)
    mask = _select_vehicle(log, vehicle_id)
    cols = ("t_s", "speed_mps", "heading_rad", "cmd_speed_mps", "cmd_heading_change_rad")
    t, speed, heading, cmd_v, cmd_dh = (np.asarray(log[c][mask], dtype=float) for c in cols)
    # Optional column: how old the measured state was when the row was written (a vehicle
    # run's telemetry age). The measurement is then placed at t - age.
    age = np.asarray(log.get("telemetry_age_s", np.zeros(len(mask)))[mask], dtype=float)
    age = np.where(np.isfinite(age), np.clip(age, 0.0, 1.0), 0.0)
    ok = np.all(np.isfinite(np.stack([t, speed, heading, cmd_v, cmd_dh])), axis=0)
    t, speed, heading, cmd_v, cmd_dh, age = (a[ok] for a in (t, speed, heading, cmd_v, cmd_dh, age))
    if len(t) < 50 or t[-1] - t[0] < 5.0:
        raise InputFileError(
            f"{log_path}: too little data to fit ({len(t)} rows, need >= 50 over >= 5 s)"
        )
    if np.ptp(cmd_v) < 0.2:
        raise InputFileError(
            f"{log_path}: the commanded speed barely changes; drive speed steps to fit"
        )
    return t, speed, heading, cmd_v, cmd_dh, age


def _align(t, speed, heading, cmd_v, cmd_dh, age, timing: str) -> _Data:
    if timing == "after-state":
        return _Data(t, speed, heading, age, t, cmd_v, heading + cmd_dh)
    return _Data(t, speed, heading, age, t[:-1], cmd_v[1:], heading[:-1] + cmd_dh[1:])


_LIFTED = 1e3  # a limit set this high never binds


def _fit_speed(
    d: _Data, lifted: frozenset[int] = frozenset()
) -> tuple[np.ndarray, float, tuple, Callable[[np.ndarray], np.ndarray]]:
    """Fit (delay, lag, accel, decel); parameters whose index is in ``lifted`` (2 = accel,
    3 = decel) are held at a value that never binds."""
    grid, (cmd_v_f,), rows = _resample(d.t, d.t_cmd, d.cmd_v)
    measured_at = np.clip(rows - np.round(d.age / _FINE_DT_S).astype(int), 0, len(grid) - 1)
    at_speed = _row_targets(len(grid), measured_at, d.speed)

    def cost(c: np.ndarray) -> np.ndarray:
        return _replay_speed(d.speed[0], cmd_v_f, c[:, 0], c[:, 1], c[:, 2], c[:, 3], at_speed)

    free = [i for i in range(4) if i not in lifted]
    bounds = [(0.0, 0.5), (0.03, 3.0), (0.1, 15.0), (0.1, 15.0)]
    log_scale = [False, True, True, True]
    points = [11, 9, 9, 9]
    step: list[float | None] = [_FINE_DT_S, None, None, None]

    def cost_free(c: np.ndarray) -> np.ndarray:
        full = np.full((len(c), 4), _LIFTED)
        full[:, free] = c
        return cost(full)

    params_free, best = _refine(
        cost_free,
        bounds=[bounds[i] for i in free],
        log_scale=[log_scale[i] for i in free],
        points=[points[i] for i in free],
        step=[step[i] for i in free],
    )
    params = np.full(4, _LIFTED)
    params[free] = params_free
    return params, best, (grid, rows, measured_at), cost


def fit_plant(
    log_path: str | Path,
    base: str | VehiclePreset = "1/10",
    name: str = "fitted",
    vehicle_id: int | None = None,
    cmd_timing: CmdTiming = "after-state",
) -> PlantFit:
    """Fit speed lag, accel/decel limits, turn-rate limit, heading lag and actuation delay
    from the log at ``log_path`` (a file or a run directory) for one vehicle.

    A limit the run never reached cannot be measured, only bounded from below: the
    result then keeps the base preset's value, or the bound if that is higher."""
    base_preset = vehicle_preset(base) if isinstance(base, str) else base
    timing = cmd_timing
    d = _aligned(log_path, vehicle_id, timing)
    (delay, tau_v, acc, dec), cost_v, grid, measured_at, unused = _fit_speed_limits(d)
    _, (cmd_v_f, cmd_h_f), _ = _resample(d.t, d.t_cmd, d.cmd_v, d.cmd_h)
    speed_f = np.interp(grid, d.t, d.speed)
    at_heading = _row_targets(len(grid), measured_at, d.heading)
    kappa = math.tan(base_preset.max_steer_rad) / base_preset.wheelbase_m
    delay_steps = int(round(delay / _FINE_DT_S))

    def heading_cost(c: np.ndarray) -> np.ndarray:
        return _replay_heading(
            d.heading[0], cmd_h_f, speed_f, kappa, delay_steps, c[:, 0], c[:, 1], at_heading
        )

    if np.ptp(np.unwrap(d.cmd_h)) > 0.2:
        rate_max, tau_h, cost_h, turn_hit = _fit_heading(heading_cost)
    else:  # no heading excitation: keep the base preset's heading loop
        rate_max, tau_h = base_preset.turn_rate_max_radps, base_preset.heading_lag_s
        cost_h, turn_hit = float(heading_cost(np.array([[rate_max, tau_h]]))[0]), False
    hit = dict(zip(_LIMIT_KEYS, (2 not in unused, 3 not in unused, turn_hit)))
    idx = np.arange(len(cmd_v_f)) - delay_steps
    target_v = np.where(idx >= 0, cmd_v_f[np.maximum(idx, 0)], d.speed[0])
    want_v = (target_v - speed_f) / tau_v
    want_h = _heading_rates_wanted(
        d.heading[0], cmd_h_f, speed_f, kappa, delay_steps, rate_max, tau_h
    )
    fitted = {"accel_max_mps2": acc, "decel_max_mps2": dec, "turn_rate_max_radps": rate_max}
    values = _limits(fitted, hit, want_v, want_h, base_preset)
    preset = dataclasses.replace(
        base_preset,
        name=name,
        speed_lag_s=round(tau_v, 4),
        accel_max_mps2=values["accel_max_mps2"],
        decel_max_mps2=values["decel_max_mps2"],
        turn_rate_max_radps=values["turn_rate_max_radps"],
        heading_lag_s=round(tau_h, 4),
        actuation_delay_s=round(delay, 4),
    )
    return PlantFit(
        preset=preset,
        speed_rms_mps=math.sqrt(cost_v),
        heading_rms_rad=math.sqrt(cost_h),
        samples=len(d.t),
        limits_hit=hit,
        cmd_timing=timing,
    )


_LIMIT_KEYS = ("accel_max_mps2", "decel_max_mps2", "turn_rate_max_radps")


def _aligned(log_path: str | Path, vehicle_id: int | None, timing: str) -> _Data:
    """One vehicle's log, its commands aligned with the states as ``timing`` says."""
    raw = _load(log_path, vehicle_id)
    if timing not in ("after-state", "before-state"):
        raise InputFileError(f"command timing must be after-state or before-state, got {timing!r}")
    return _align(*raw, timing)


def _fit_speed_limits(
    d: _Data,
) -> tuple[tuple[float, float, float, float], float, np.ndarray, Any, frozenset[int]]:
    """(delay s, lag s, accel and decel limits m/s²) fitted, their cost, the replay grid
    and where rows were measured, and the limits the run never hit (2 accel, 3 decel),
    which are refitted out of the way."""
    speed_params, cost_v, (grid, rows, measured_at), speed_cost = _fit_speed(d)
    unused = frozenset(
        i for i in (2, 3) if not _limit_matters(speed_cost, list(speed_params), i, cost_v)
    )
    if unused:
        speed_params, cost_v, _, _ = _fit_speed(d, lifted=unused)
    delay, tau_v, acc, dec = (float(x) for x in speed_params)
    return (delay, tau_v, acc, dec), cost_v, grid, measured_at, unused


def _limit_matters(
    cost_fn: Callable[[np.ndarray], np.ndarray], params: list[float], i: int, best: float
) -> bool:
    """Does limit ``i`` matter? Lifting it must make the fit clearly worse; otherwise the
    run never pushed against it: its value is only bounded from below by what was needed,
    and the other parameters are refitted without it (a free limit would distort them)."""
    lifted = list(params)
    lifted[i] = _LIFTED
    return float(cost_fn(np.array([lifted]))[0]) > 1.2 * best + 1e-10


def _fit_heading(
    heading_cost: Callable[[np.ndarray], np.ndarray],
) -> tuple[float, float, float, bool]:
    """Turn-rate limit (rad/s) and heading lag (s) fitted: ``(rate, lag, cost, hit)``; an
    unhit rate limit is left out and the lag refitted alone."""
    (rate_max, tau_h), cost_h = _refine(
        heading_cost,
        bounds=[(0.05, 6.0), (0.02, 2.0)],
        log_scale=[True, True],
        points=[13, 11],
        step=[None, None],
    )
    rate_max, tau_h = float(rate_max), float(tau_h)
    turn_hit = _limit_matters(heading_cost, [rate_max, tau_h], 0, cost_h)
    if not turn_hit:  # refit the heading lag alone, the rate limit out of the way
        (tau_h,), cost_h = _refine(
            lambda c: heading_cost(np.column_stack([np.full(len(c), _LIFTED), c[:, 0]])),
            bounds=[(0.02, 2.0)],
            log_scale=[True],
            points=[25],
            step=[None],
        )
        tau_h = float(tau_h)
    return rate_max, tau_h, cost_h, turn_hit


def _limits(
    fitted: dict[str, float],
    hit: dict[str, bool],
    want_v: np.ndarray,
    want_h: np.ndarray,
    base_preset: VehiclePreset,
) -> dict[str, float]:
    """The limits to keep: fitted where the run hit them, else the base preset's unless
    the run needed more (the speed changes ``want_v`` m/s² and rates ``want_h`` rad/s it
    asked for)."""
    needed = {
        "accel_max_mps2": float(max(0.0, want_v.max())),
        "decel_max_mps2": float(max(0.0, -want_v.min())),
        "turn_rate_max_radps": float(want_h.max()),
    }
    values = dict(fitted)
    for key, was_hit in hit.items():
        if was_hit:
            values[key] = round(values[key], 4)
        else:  # unmeasured: the base value unless the run needed more
            base_value = getattr(base_preset, key)
            values[key] = base_value if base_value >= needed[key] else round(needed[key], 4)
    return values


def _heading_rates_wanted(
    h0: float,
    cmd: np.ndarray,
    speed: np.ndarray,
    kappa: float,
    delay_steps: int,
    rate_max: float,
    tau: float,
) -> np.ndarray:
    """|yaw rate| the heading loop asked for (before the turn-rate cap) along the replay,
    where the curvature cap did not bind harder; rad/s."""
    h = h0
    tau = max(tau, _FINE_DT_S)
    out = np.zeros(len(cmd))
    for i in range(len(cmd)):
        target = cmd[i - delay_steps] if i >= delay_steps else h0
        err = (target - h + math.pi) % (2 * math.pi) - math.pi
        curvature_cap = abs(speed[i]) * kappa
        wanted = abs(err / tau)
        out[i] = wanted if curvature_cap > rate_max else 0.0
        cap = min(rate_max, curvature_cap)
        h += max(-cap, min(cap, err / tau)) * _FINE_DT_S
    return out


def format_fit(fit: PlantFit) -> str:
    """A short human summary of a fit."""
    p = fit.preset

    def limit(key: str) -> str:
        return "" if fit.limits_hit[key] else "  (never reached: not measured, kept base/bound)"

    lines = [
        f"fitted preset {p.name!r} from {fit.samples} rows (commands {fit.cmd_timing})",
        f"  actuation_delay_s   {p.actuation_delay_s:.3f}",
        f"  speed_lag_s         {p.speed_lag_s:.3f}",
        f"  accel_max_mps2      {p.accel_max_mps2:.3f}{limit('accel_max_mps2')}",
        f"  decel_max_mps2      {p.decel_max_mps2:.3f}{limit('decel_max_mps2')}",
        f"  turn_rate_max_radps {p.turn_rate_max_radps:.3f} "
        f"({math.degrees(p.turn_rate_max_radps):.1f} deg/s){limit('turn_rate_max_radps')}",
        f"  heading_lag_s       {p.heading_lag_s:.3f}",
        f"  residual RMS: speed {fit.speed_rms_mps:.4f} m/s, heading "
        f"{math.degrees(fit.heading_rms_rad):.2f} deg",
    ]
    return "\n".join(lines)


def run_fit_plant_cli(args: argparse.Namespace) -> int:
    """``openconvoy fit-plant LOG_DIR... [--model lag|pi] [--out preset.toml] [--name] [--base]
    [--vehicle-id] [--source]``."""
    from openconvoy.outputs import check_output_file

    logs = args.log if isinstance(args.log, list) else [args.log]
    if getattr(args, "convoy", None) or getattr(args, "out_convoy", None):
        return _calibrate_cli(args, logs)
    check_output_file(args.out or f"{args.name}.toml", "--out")
    args.base = args.base or "1/10"
    if getattr(args, "model", "lag") == "pi":
        pi_fit = fit_pi_plant(
            logs,
            base=args.base,
            name=args.name,
            vehicle_id=args.vehicle_id,
            source=args.source,
            cmd_timing=getattr(args, "cmd_timing", "after-state"),
        )
        print(format_pi_fit(pi_fit))
        preset = pi_fit.preset
    else:
        from openconvoy.experiments.recording import is_recording

        if len(logs) != 1 or is_recording(logs[0]):
            raise ConfigError(
                "the lag model fits one run's log; use --model pi for recordings or several inputs"
            )
        fit = fit_plant(
            logs[0],
            base=args.base,
            name=args.name,
            vehicle_id=args.vehicle_id,
            cmd_timing=getattr(args, "cmd_timing", "after-state"),
        )
        print(format_fit(fit))
        preset = fit.preset
    out = Path(args.out or f"{args.name}.toml")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(preset_to_toml(preset))
    print(f"wrote {out}")
    return 0


def _calibrate_cli(args: argparse.Namespace, logs: list[str]) -> int:
    """``fit-plant RUN_DIR --convoy CONVOY.toml --out-convoy FITTED.toml``."""
    from openconvoy.experiments.calibration import calibrate, format_calibration
    from openconvoy.outputs import check_output_file

    if not (args.convoy and args.out_convoy):
        raise ConfigError("--convoy and --out-convoy go together (calibrate a vehicle run)")
    if len(logs) != 1 or not Path(logs[0]).is_dir():
        raise ConfigError("--convoy calibrates one vehicle run: give its run directory")
    check_output_file(args.out_convoy, "--out-convoy")
    result = calibrate(logs[0], args.convoy, args.out_convoy, base=args.base)
    print(format_calibration(result))
    return 0


# --- The autopilot's PI speed loop (``speed_loop = "pi"``), from logs or recordings -------

_PI_DT_S = 0.02  # the replay step: the plant's pi substep (PI_MAX_DT_S), the autopilots' loop
_PI_SPEED_KEYS = (
    "actuation_delay_s",
    "accel_max_mps2",
    "decel_max_mps2",
    "speed_kp",
    "speed_ki",
    "speed_ff",
    "drive_lag_s",
    "breakaway_mps",
    "drive_drag_per_mps",
)
_KINETIC_KEY = "kinetic_friction_mps"
"""Fitted by a second search after the others (``_fit_pi_speed``): the first search over
``_PI_SPEED_KEYS`` draws as before, and the second is kept only where kinetic friction
clearly lowers the speed cost, so fits without it are unchanged."""
# (low, high, log scale) per parameter; the search starts at the base preset when it has a
# pi loop, else at a generic loop (unit gains and feed-forward, 1 s drive lag).
_PI_SPEED_BOUNDS = (
    (0.0, 0.6, False),
    (0.2, 10.0, True),
    (0.2, 10.0, True),
    (1e-3, 20.0, True),
    (1e-3, 20.0, True),
    (0.3, 2.5, False),
    (0.05, 5.0, True),
    (0.0, 1.5, False),
    (0.0, 1.0, False),
)
_PI_SPEED_PRIOR = (0.1, 2.0, 2.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.0)
_HEADING_ERR_CAP_RAD = math.radians(15.0)
_SPEED_ERR_CAP_MPS = 0.3
FRICTION_MATTERS = 1.2
"""A fitted static friction is kept only if dropping it raises the speed cost this much."""
_PI_HEADING_KEYS = (
    "heading_delay_s",
    "heading_lag_s",
    "turn_rate_max_radps",
    "yaw_accel_max_radps2",
    "lateral_accel_max_mps2",
    "max_steer_rad",
)
_PI_HEADING_BOUNDS = (
    (0.0, 0.5, False),
    (0.05, 2.0, True),
    (0.3, 6.0, True),
    (0.3, 60.0, True),
    (0.5, 30.0, True),
    (0.05, 1.2, True),
)
_PI_HEADING_PRIOR = (0.02, 0.5, 2.09, 2.09, 10.0, 0.35)


@dataclass(frozen=True)
class _Series:
    """One contiguous stretch for the pi fit: measurements and commands (s, m/s, ENU rad)."""

    t: np.ndarray
    speed: np.ndarray
    heading: np.ndarray
    t_cmd: np.ndarray
    cmd_v: np.ndarray
    cmd_h: np.ndarray


def _held(series: _Series, *values: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """The pi replay grid (``_PI_DT_S``) of a stretch, commands held from their send times,
    and the grid index of each measurement."""
    t0 = series.t_cmd[0]
    n = int(round((series.t[-1] - t0) / _PI_DT_S)) + 1
    grid = t0 + _PI_DT_S * np.arange(n)
    k = np.clip(
        np.searchsorted(series.t_cmd, grid + 1e-9, side="right") - 1, 0, len(series.t_cmd) - 1
    )
    rows = np.clip(np.round((series.t - t0) / _PI_DT_S).astype(int), 0, n - 1)
    return grid, [v[k] for v in values], rows


def _pi_speed_sse(series: _Series, c: np.ndarray) -> np.ndarray:
    """Sum of squared speed errors at the measurements for candidates ``c`` (k, 9) in
    ``_PI_SPEED_KEYS`` order, or (k, 10) with the kinetic friction last, replaying
    ``envs.plant``'s pi loop at ``_PI_DT_S`` (``friction_speed``'s rules on arrays)."""
    _, (cmd,), rows = _held(series, series.cmd_v)
    h = _PI_DT_S
    delay = np.round(c[:, 0] / h).astype(int)
    acc, dec, kp, ki, ff, tau, brk, drag = (c[:, i] for i in range(1, 9))
    kin = c[:, 9] if c.shape[1] > 9 else np.zeros(len(c))
    held_below = np.maximum(brk, kin)
    v0 = float(series.speed[0])
    v = np.full(len(c), v0)
    r = v.copy()
    integ = v0 * (1.0 - ff)
    out = np.empty((len(cmd), len(c)))
    stop = 0.1
    for i in range(len(cmd)):
        j = i - delay
        v_cmd = np.where(j >= 0, cmd[np.maximum(j, 0)], v0)
        lim = np.where(np.abs(v_cmd) > np.abs(r), acc, dec) * h
        r = r + np.clip(v_cmd - r, -lim, lim)
        err = r - v
        stopped = (r == 0.0) & (np.abs(v) <= stop)
        integ = np.where(stopped, 0.0, integ + ki * err * h)
        drive = np.where(stopped, 0.0, ff * r + kp * err + integ)
        kf = kin * np.where(v == 0.0, np.sign(drive), np.sign(v))
        dv = (drive - v - drag * v * np.abs(v) - kf) / tau * h
        stuck = (np.abs(drive) < held_below) & ((v == 0.0) | ((v + dv) * v < 0.0) | stopped)
        v = np.where(stuck, 0.0, v + dv)
        out[i] = v
    # The measurement at grid row k is the state after k steps.
    got = np.concatenate([np.full((1, len(c)), v0), out])[rows]
    # Robust: stick-slip (PX4 SIH at 0.7 m/s) is not in the model; a sample off by more
    # than the cap counts as the cap, so it cannot drag the rest of the fit.
    return np.minimum((got - series.speed[:, None]) ** 2, _SPEED_ERR_CAP_MPS**2).sum(axis=0)


def _pi_heading_sse(series: _Series, c: np.ndarray, wheelbase_m: float) -> np.ndarray:
    """Sum of squared (wrapped) heading errors for candidates ``c`` (k, 6) in
    ``_PI_HEADING_KEYS`` order; the measured speed drives the curvature caps."""
    grid, (cmd,), rows = _held(series, np.unwrap(series.cmd_h))
    speed = np.interp(grid, series.t, series.speed)
    h = _PI_DT_S
    delay = np.round(c[:, 0] / h).astype(int)
    tau, rate_max, yaw_acc, alat, steer = (c[:, i] for i in range(1, 6))
    kappa = np.tan(steer) / wheelbase_m
    h0 = float(series.heading[0])
    psi = np.full(len(c), h0)
    rate_des = np.zeros(len(c))
    out = np.empty((len(cmd), len(c)))
    for i in range(len(cmd)):
        j = i - delay
        target = np.where(j >= 0, cmd[np.maximum(j, 0)], h0)
        err = (target - psi + math.pi) % (2 * math.pi) - math.pi
        wanted = np.clip(err / np.maximum(tau, h), -rate_max, rate_max)
        rate_des = np.clip(wanted, rate_des - yaw_acc * h, rate_des + yaw_acc * h)
        s = abs(speed[i])
        cap = np.minimum(s * kappa, alat / max(s, 1e-9))
        psi = psi + np.clip(rate_des, -cap, cap) * h
        out[i] = psi
    got = np.concatenate([np.full((1, len(c)), h0), out])[rows]
    err = ((got - series.heading[:, None]) + math.pi) % (2 * math.pi) - math.pi
    # Robust: a 180 deg step turns either way by a hair of residual error (README §4), so a
    # candidate turning the other way is off by up to 180 deg for seconds; cap each sample.
    return np.minimum(err**2, _HEADING_ERR_CAP_RAD**2).sum(axis=0)


def _cem(
    cost,
    prior: Sequence[float],
    bounds: Sequence[tuple[float, float, bool]],
    rounds: int = 14,
    population: int = 160,
    elite: int = 16,
    seed: int = 0,
) -> tuple[np.ndarray, float]:
    """Minimize ``cost`` ((k, d) candidates -> k costs) by the cross-entropy method: sample
    around the mean, refit mean and spread to the best, repeat. Deterministic (seeded);
    works through the loops' kinks (stop logic, friction, the discrete delay) where a
    gradient method would not."""
    rng = np.random.default_rng(seed)
    raw_cost = cost

    def safe_cost(x: np.ndarray) -> np.ndarray:  # unstable candidates overflow: never the best
        with np.errstate(all="ignore"):
            c = raw_cost(x)
        return np.where(np.isfinite(c), c, np.inf)

    lo = np.array([math.log(b[0]) if b[2] else b[0] for b in bounds])
    hi = np.array([math.log(b[1]) if b[2] else b[1] for b in bounds])
    logs = np.array([b[2] for b in bounds])

    def to_z(x: np.ndarray) -> np.ndarray:
        return np.where(logs, np.log(np.maximum(x, 1e-12)), x)

    def from_z(z: np.ndarray) -> np.ndarray:
        return np.where(logs, np.exp(z), z)

    mean = np.clip(to_z(np.asarray(prior, dtype=float)), lo, hi)
    spread = (hi - lo) / 4.0
    best_z, best_cost = mean.copy(), float(safe_cost(from_z(mean[None, :]))[0])
    for _ in range(rounds):
        z = np.clip(mean + spread * rng.standard_normal((population, len(mean))), lo, hi)
        z[0] = best_z  # keep the best so far
        costs = safe_cost(from_z(z))
        order = np.argsort(costs)[:elite]
        if costs[order[0]] < best_cost:
            best_z, best_cost = z[order[0]].copy(), float(costs[order[0]])
        mean = z[order].mean(axis=0)
        spread = np.maximum(z[order].std(axis=0), (hi - lo) * 1e-3)
    return from_z(best_z), best_cost


@dataclass(frozen=True)
class PiFit:
    """Result of a pi fit: the preset, residual RMS, samples and where the data came from."""

    preset: VehiclePreset
    speed_rms_mps: float
    heading_rms_rad: float
    samples: int
    source: str


def _series_from(
    path: str | Path,
    vehicle_id: int | None,
    source: str,
    cmd_timing: str = "after-state",
    telemetry_age: bool = True,
) -> tuple[list[_Series], str]:
    from openconvoy.experiments.recording import is_recording, read_recording

    if is_recording(path):
        rec = read_recording(path, source=source)
        return [
            _Series(s.t, s.speed, s.heading, s.t_cmd, s.cmd_speed, s.cmd_heading)
            for s in rec.segments
        ], f"{rec.autopilot} recording"
    d = _align(*_load(path, vehicle_id), cmd_timing)
    # A row's state is as old as its telemetry; or, for the loop delay a controller sees,
    # as the row says (telemetry_age False).
    t_meas = d.t - d.age if telemetry_age else d.t
    return [_Series(t_meas, d.speed, d.heading, d.t_cmd, d.cmd_v, d.cmd_h)], "log"


def fit_pi_plant(
    paths: Sequence[str | Path],
    base: str | VehiclePreset = "ardupilot-rover",
    name: str = "fitted",
    vehicle_id: int | None = None,
    source: str = "telemetry",
    rounds: int = 14,
    population: int = 160,
    cmd_timing: CmdTiming = "after-state",
    telemetry_age: bool = True,
) -> PiFit:
    """Fit the autopilot's PI speed loop (delay, ramp limits, gains, feed-forward, drive
    lag, static friction) and its heading loop (delay, lag, rate and yaw-accel limits,
    lateral accel, steering lock) from deploy logs and/or MAVLink recordings.

    Speed is fitted on every stretch whose commanded speed changes, heading on every
    stretch whose commanded heading changes; the other loop keeps the base preset's values
    when no stretch excites it. Size and speed cap come from the base preset. The search
    (cross-entropy, seeded) runs ``rounds`` rounds of ``population`` candidates."""
    base_preset = vehicle_preset(base) if isinstance(base, str) else base
    series: list[_Series] = []
    kinds = []
    for p in paths:
        got, kind = _series_from(p, vehicle_id, source, cmd_timing, telemetry_age)
        series += got
        kinds.append(kind)
    speed_series = [s for s in series if np.ptp(s.cmd_v) >= 0.2]
    heading_series = [s for s in series if np.ptp(np.unwrap(s.cmd_h)) > 0.2]
    values: dict[str, float] = {}
    samples = sum(len(s.t) for s in series)
    speed_rms = heading_rms = math.nan
    if speed_series:
        fitted, speed_rms = _fit_pi_speed(speed_series, base_preset, rounds, population)
        values.update(fitted)
    if heading_series:
        fitted, heading_rms = _fit_pi_heading(heading_series, base_preset, rounds, population)
        values.update(fitted)
    if not values:
        raise InputFileError("nothing to fit: no stretch changes the commanded speed or heading")
    # An unfitted heading loop keeps the base's heading delay, whatever the speed delay is.
    values.setdefault("heading_delay_s", base_preset.heading_delay)
    rounded: dict[str, Any] = {k: round(v, 4) for k, v in values.items()}
    preset = dataclasses.replace(base_preset, name=name, speed_loop="pi", **rounded)
    return PiFit(preset, speed_rms, heading_rms, samples, " + ".join(sorted(set(kinds))))


def pi_speed_rms(series: Sequence[_Series], presets: Sequence[VehiclePreset]) -> np.ndarray:
    """Each preset's speed RMS (m/s) replaying ``series`` (its pi loop's parameters)."""
    keys = (*_PI_SPEED_KEYS, _KINETIC_KEY)
    c = np.array([[getattr(p, k) for k in keys] for p in presets], dtype=float)
    n = sum(len(s.t) for s in series)
    with np.errstate(all="ignore"):
        sse = sum(_pi_speed_sse(s, c) for s in series)
    return np.sqrt(np.asarray(sse) / max(n, 1))


def _fit_pi_speed(
    speed_series: list[_Series], base_preset: VehiclePreset, rounds: int, population: int
) -> tuple[dict[str, float], float]:
    """The PI speed loop's parameters fitted on ``speed_series``, and the RMS error (m/s)."""
    n = sum(len(s.t) for s in speed_series)
    prior = (
        [getattr(base_preset, k) for k in _PI_SPEED_KEYS]
        if base_preset.speed_loop == "pi"
        else list(_PI_SPEED_PRIOR)
    )

    def speed_cost(c: np.ndarray) -> np.ndarray:
        return cast(np.ndarray, sum(_pi_speed_sse(s, c) for s in speed_series)) / n

    best, cost = _cem(speed_cost, prior, _PI_SPEED_BOUNDS, rounds=rounds, population=population)
    # Static friction only where the data needs it: without it the fit must be clearly
    # worse (a vehicle that would not start), not just a shade off in a stop's tail.
    frictionless = best.copy()
    frictionless[7] = 0.0
    with np.errstate(all="ignore"):
        cost_free = float(speed_cost(frictionless[None, :])[0])
    if cost_free <= FRICTION_MATTERS * cost:
        best, cost = frictionless, cost_free
    values = dict(zip(_PI_SPEED_KEYS, (float(x) for x in best)))
    values[_KINETIC_KEY] = 0.0
    # Kinetic friction (stick-slip, PX4 SIH's rolling friction): a second search over the
    # loop with it, from the first's best (kinetic friction at half the static). Kept where
    # it clearly lowers the speed cost (``FRICTION_MATTERS``), so a loop without friction
    # (ArduPilot's) stays as the first search gave it.
    start = [*best[:7], max(best[7], 0.5), best[8], 0.5 * max(best[7], 0.5)]
    bounds = (*_PI_SPEED_BOUNDS, (0.0, 1.5, False))
    best_k, cost_k = _cem(speed_cost, start, bounds, rounds=rounds, population=population)
    if FRICTION_MATTERS * cost_k < cost and best_k[9] > 0.0:
        cost = cost_k
        values = dict(zip(_PI_SPEED_KEYS, (float(x) for x in best_k[:9])))
        values[_KINETIC_KEY] = float(best_k[9])
    values["actuation_delay_s"] = round(values["actuation_delay_s"] / _PI_DT_S) * _PI_DT_S
    return values, math.sqrt(cost)


def _fit_pi_heading(
    heading_series: list[_Series], base_preset: VehiclePreset, rounds: int, population: int
) -> tuple[dict[str, float], float]:
    """The heading loop's parameters fitted on ``heading_series``, and the RMS error (rad)."""
    n = sum(len(s.t) for s in heading_series)
    prior = [
        base_preset.heading_delay if k == "heading_delay_s" else getattr(base_preset, k)
        for k in _PI_HEADING_KEYS
    ]
    prior = [min(x, 1e3) for x in prior]
    best, cost = _cem(
        lambda c: sum(_pi_heading_sse(s, c, base_preset.wheelbase_m) for s in heading_series) / n,
        prior,
        _PI_HEADING_BOUNDS,
        rounds=rounds,
        population=population,
    )
    values = dict(zip(_PI_HEADING_KEYS, (float(x) for x in best)))
    values["heading_delay_s"] = round(values["heading_delay_s"] / _PI_DT_S) * _PI_DT_S
    return values, math.sqrt(cost)


def format_pi_fit(fit: PiFit) -> str:
    """A short human summary of a pi fit."""
    p = fit.preset
    lines = [
        f"fitted preset {p.name!r} (autopilot PI speed loop) from {fit.samples} samples "
        f"({fit.source})"
    ]
    for key in (*_PI_SPEED_KEYS, _KINETIC_KEY, *_PI_HEADING_KEYS):
        value = p.heading_delay if key == "heading_delay_s" else getattr(p, key)
        extra = f" ({math.degrees(value):.1f} deg/s)" if key == "turn_rate_max_radps" else ""
        lines.append(f"  {key:<24}{value:.4g}{extra}")
    lines.append(
        f"  residual RMS: speed {fit.speed_rms_mps:.4f} m/s, heading "
        f"{math.degrees(fit.heading_rms_rad):.2f} deg"
    )
    return "\n".join(lines)
