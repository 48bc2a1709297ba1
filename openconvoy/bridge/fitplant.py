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

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
        speed_limits_hit: whether the replay hit the acceleration / deceleration limits
            at all (if not, those limits are only lower bounds).
    """

    preset: VehiclePreset
    speed_rms_mps: float
    heading_rms_rad: float
    samples: int
    speed_limits_hit: tuple[bool, bool]


def _select_vehicle(log: dict[str, np.ndarray], vehicle_id: int | None) -> np.ndarray:
    ids = np.unique(log["vehicle_id"])
    if vehicle_id is None:
        if len(ids) != 1:
            raise ValueError(
                f"the log holds vehicles {', '.join(map(str, ids))}: choose one with --vehicle-id"
            )
        vehicle_id = int(ids[0])
    mask = log["vehicle_id"] == vehicle_id
    if not mask.any():
        raise ValueError(f"no rows for vehicle {vehicle_id} in the log (has {', '.join(map(str, ids))})")
    return mask


def _resample(t: np.ndarray, *series: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Fine time grid from t[0] to t[-1]; commands held (zero-order) between rows.
    Returns (grid, held series, index of each log row on the grid)."""
    n = int(round((t[-1] - t[0]) / _FINE_DT_S)) + 1
    grid = t[0] + _FINE_DT_S * np.arange(n)
    rows_on_grid = np.clip(np.round((t - t[0]) / _FINE_DT_S).astype(int), 0, n - 1)
    # Row k's command holds from its own grid point on (indices, not float comparisons).
    row_of = np.clip(np.searchsorted(rows_on_grid, np.arange(n), side="right") - 1, 0, len(t) - 1)
    return grid, [s[row_of] for s in series], rows_on_grid


def _row_targets(n: int, rows: np.ndarray, measured: np.ndarray) -> list[list[float]]:
    """For each fine step, the measured values of the log rows that fall on it."""
    at: list[list[float]] = [[] for _ in range(n)]
    for r, m in zip(rows, measured):
        at[r].append(float(m))
    return at


def _replay_speed(
    v0: float, cmd: np.ndarray, delay: np.ndarray, tau: np.ndarray, acc: np.ndarray,
    dec: np.ndarray, at: list[list[float]],
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
        err = cmd[np.maximum(i - steps, 0)] - v
        dv = np.clip(err / tau, -dec, acc) * _FINE_DT_S
        v = v + np.where(np.abs(dv) > np.abs(err), err, dv)  # never overshoot in one step
    return sse / max(count, 1)


def _replay_heading(
    h0: float, cmd: np.ndarray, speed: np.ndarray, kappa: float, delay_steps: int,
    rate_max: np.ndarray, tau: np.ndarray, at: list[list[float]],
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
        err = (cmd[max(i - delay_steps, 0)] - h + math.pi) % (2 * math.pi) - math.pi
        cap = np.minimum(rate_max, abs(speed[i]) * kappa)
        h = h + np.clip(err / tau, -cap, cap) * _FINE_DT_S
    return sse / max(count, 1)


def _refine(
    score, bounds: list[tuple[float, float]], log_scale: list[bool], points: list[int],
    step: list[float | None], rounds: int = 8, shrink: float = 0.5,
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
            if step[i] is not None and best is not None:
                values = best[i] + step[i] * np.arange(-4, 5)
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


def fit_plant(
    log_path: str | Path,
    base: str | VehiclePreset = "1/10",
    name: str = "fitted",
    vehicle_id: int | None = None,
) -> PlantFit:
    """Fit speed lag, accel/decel limits, turn-rate limit, heading lag and actuation delay
    from the log at ``log_path`` (a file or a run directory) for one vehicle."""
    base_preset = vehicle_preset(base) if isinstance(base, str) else base
    log = read_log(log_path)
    mask = _select_vehicle(log, vehicle_id)
    cols = ("t_s", "speed_mps", "heading_rad", "cmd_speed_mps", "cmd_heading_change_rad")
    t, speed, heading, cmd_v, cmd_dh = (np.asarray(log[c][mask], dtype=float) for c in cols)
    # Optional column: how old the measured state was when the row was written (a vehicle
    # run's telemetry age). The measurement is then placed at t - age.
    age = np.asarray(log.get("telemetry_age_s", np.zeros(len(mask)))[mask], dtype=float)
    age = np.where(np.isfinite(age), np.clip(age, 0.0, 1.0), 0.0)
    ok = np.all(np.isfinite(np.stack([t, speed, heading, cmd_v, cmd_dh])), axis=0)
    t, speed, heading, cmd_v, cmd_dh, age = (
        a[ok] for a in (t, speed, heading, cmd_v, cmd_dh, age)
    )
    if len(t) < 50 or t[-1] - t[0] < 5.0:
        raise ValueError(f"{log_path}: too little data to fit ({len(t)} rows, need >= 50 over >= 5 s)")
    if np.ptp(cmd_v) < 0.2:
        raise ValueError(f"{log_path}: the commanded speed barely changes; drive speed steps to fit")
    cmd_h = heading + cmd_dh
    grid, (cmd_v_f, cmd_h_f), rows = _resample(t, cmd_v, cmd_h)
    speed_f = np.interp(grid, t, speed)

    measured_at = np.clip(rows - np.round(age / _FINE_DT_S).astype(int), 0, len(grid) - 1)
    at_speed = _row_targets(len(grid), measured_at, speed)
    at_heading = _row_targets(len(grid), measured_at, heading)

    def speed_cost(c: np.ndarray) -> np.ndarray:
        return _replay_speed(speed[0], cmd_v_f, c[:, 0], c[:, 1], c[:, 2], c[:, 3], at_speed)

    (delay, tau_v, acc, dec), cost_v = _refine(
        speed_cost,
        bounds=[(0.0, 0.5), (0.03, 3.0), (0.1, 15.0), (0.1, 15.0)],
        log_scale=[False, True, True, True],
        points=[11, 9, 9, 9],
        step=[_FINE_DT_S, None, None, None],
    )
    kappa = math.tan(base_preset.max_steer_rad) / base_preset.wheelbase_m
    delay_steps = int(round(delay / _FINE_DT_S))

    def heading_cost(c: np.ndarray) -> np.ndarray:
        return _replay_heading(
            heading[0], cmd_h_f, speed_f, kappa, delay_steps, c[:, 0], c[:, 1], at_heading
        )

    turning = np.ptp(np.unwrap(cmd_h)) > 0.2
    if turning:
        (rate_max, tau_h), cost_h = _refine(
            heading_cost, bounds=[(0.05, 6.0), (0.02, 2.0)], log_scale=[True, True], points=[13, 11],
            step=[None, None],
        )
    else:  # no heading excitation: keep the base preset's heading loop
        rate_max, tau_h = base_preset.turn_rate_max_radps, base_preset.heading_lag_s
        cost_h = float(heading_cost(np.array([[rate_max, tau_h]]))[0])

    # Were the limits active anywhere in the replay? Otherwise they are lower bounds only.
    steps = int(round(delay / _FINE_DT_S))
    target = cmd_v_f[np.maximum(np.arange(len(cmd_v_f)) - steps, 0)]
    rate_wanted = (target - speed_f) / tau_v
    limits_hit = (bool(np.any(rate_wanted > acc * 1.02)), bool(np.any(rate_wanted < -dec * 1.02)))

    preset = dataclasses.replace(
        base_preset, name=name, speed_lag_s=round(float(tau_v), 4),
        accel_max_mps2=round(float(acc), 4), decel_max_mps2=round(float(dec), 4),
        turn_rate_max_radps=round(float(rate_max), 4), heading_lag_s=round(float(tau_h), 4),
        actuation_delay_s=round(float(delay), 4),
    )
    return PlantFit(
        preset=preset, speed_rms_mps=math.sqrt(cost_v), heading_rms_rad=math.sqrt(cost_h),
        samples=len(t), speed_limits_hit=limits_hit,
    )


def format_fit(fit: PlantFit) -> str:
    """A short human summary of a fit."""
    p = fit.preset
    lines = [
        f"fitted preset {p.name!r} from {fit.samples} rows",
        f"  actuation_delay_s   {p.actuation_delay_s:.3f}",
        f"  speed_lag_s         {p.speed_lag_s:.3f}",
        f"  accel_max_mps2      {p.accel_max_mps2:.3f}"
        + ("" if fit.speed_limits_hit[0] else "  (never reached: a lower bound)"),
        f"  decel_max_mps2      {p.decel_max_mps2:.3f}"
        + ("" if fit.speed_limits_hit[1] else "  (never reached: a lower bound)"),
        f"  turn_rate_max_radps {p.turn_rate_max_radps:.3f} ({math.degrees(p.turn_rate_max_radps):.1f} deg/s)",
        f"  heading_lag_s       {p.heading_lag_s:.3f}",
        f"  residual RMS: speed {fit.speed_rms_mps:.4f} m/s, heading {math.degrees(fit.heading_rms_rad):.2f} deg",
    ]
    return "\n".join(lines)


def run_fit_plant_cli(args: object) -> int:
    """``openconvoy fit-plant LOG_DIR [--out preset.toml] [--name] [--base] [--vehicle-id]``."""
    fit = fit_plant(
        args.log, base=args.base, name=args.name, vehicle_id=args.vehicle_id  # type: ignore[attr-defined]
    )
    print(format_fit(fit))
    out = Path(args.out or f"{args.name}.toml")  # type: ignore[attr-defined]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(preset_to_toml(fit.preset))
    print(f"wrote {out}")
    return 0
