"""Figures: a single run's (trajectories, gaps, speeds) and a sweep's (the paper's Figs 4–8,
plus minimum gap vs PER).

Matplotlib with the Agg backend (files only, no display); every axis is labelled with
its unit and every figure with several lines has a legend.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from openconvoy.core import metrics as mt

if TYPE_CHECKING:
    from openconvoy.experiments.sweep import SweepResult

SWEEP_FIGURES: tuple[str, ...] = (
    "fig4_trajectories.png",
    "fig5_speed_difference.png",
    "fig6_max_platooning_error.png",
    "fig7_mean_speed_difference_vs_per.png",
    "fig8_p95_platooning_error_vs_per.png",
    "fig9_min_gap_vs_per.png",
)
RUN_FIGURES: tuple[str, ...] = ("trajectories.png", "gaps.png", "speeds.png")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    fig.tight_layout()
    # Fixed metadata so identical figures are identical files.
    fig.savefig(path, dpi=110, metadata={"Software": None})
    _plt().close(fig)


def _vehicle_label(vid: int) -> str:
    return "leader" if vid == 0 else f"follower {vid}"


# --- one run -----------------------------------------------------------------------------


def run_figures(log: mt.Columns, out_dir: str | Path, title: str = "") -> list[Path]:
    """Trajectories (ENU), gaps to the predecessor with desired gaps, and speeds over time."""
    plt = _plt()
    out = Path(out_dir)
    paths = [out / name for name in RUN_FIGURES]
    ids = mt.vehicle_ids(log)
    t_all = np.asarray(log["t_s"], dtype=float)
    vid_all = np.asarray(log["vehicle_id"])

    fig, ax = plt.subplots(figsize=(8, 4))
    x_all, y_all = np.asarray(log["x_m"], dtype=float), np.asarray(log["y_m"], dtype=float)
    lead = vid_all == 0
    line = straight_line(x_all[lead], y_all[lead])
    for vid in ids:
        r = vid_all == vid
        if line is None:
            ax.plot(x_all[r], y_all[r], label=_vehicle_label(vid))
        else:
            along, off = road_frame(x_all[r], y_all[r], line)
            ax.plot(along, 100.0 * off, label=_vehicle_label(vid))
    if line is None:
        ax.set_aspect("equal", adjustable="datalim")  # curves undistorted
        ax.set_xlabel("east x (m)")
        ax.set_ylabel("north y (m)")
        ax.set_title(f"Trajectories {title}".strip())
    else:
        # A straight road: metres of road against centimetres off the leader's line, so
        # a lateral wobble reads in honest units instead of filling a ±0.05 m axis.
        ax.set_xlabel("distance along the road (m)")
        ax.set_ylabel("lateral offset from the leader's line (cm)")
        ax.set_title(f"Lateral deviation on the straight road {title}".strip())
    ax.legend()
    _save(fig, paths[0])

    fig, ax = plt.subplots(figsize=(8, 4))
    gaps = mt.follower_gaps(log)
    desired = np.asarray(log["desired_gap_m"], dtype=float)
    for vid, (t, g) in gaps.items():
        line = ax.plot(t, g, label=f"{_vehicle_label(vid)} gap")[0]
        r = vid_all == vid
        ax.plot(
            t_all[r],
            desired[r],
            "--",
            color=line.get_color(),
            label=f"{_vehicle_label(vid)} desired",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("gap to predecessor, centre to centre (m)")
    ax.set_title(f"Gaps {title}".strip())
    ax.legend()
    _save(fig, paths[1])

    fig, ax = plt.subplots(figsize=(8, 4))
    speed = np.asarray(log["speed_mps"], dtype=float)
    for vid in ids:
        r = vid_all == vid
        ax.plot(t_all[r], speed[r], label=_vehicle_label(vid))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("speed (m/s)")
    ax.set_title(f"Speeds {title}".strip())
    ax.legend()
    _save(fig, paths[2])
    return paths


def straight_line(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The leader's straight line ``(origin, unit direction)`` (m) when its path (``x``,
    ``y`` in m) stays within 0.5 m of the chord from its first to its last point and is
    longer than 1 m; None for a curved road or a convoy at rest."""
    pts = np.stack([x, y], axis=1)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        return None
    chord = pts[-1] - pts[0]
    length = float(np.hypot(*chord))
    if length < 1.0:
        return None
    u = chord / length
    off = (pts - pts[0]) @ np.array([-u[1], u[0]])
    return (pts[0], u) if float(np.max(np.abs(off))) <= 0.5 else None


def road_frame(
    x: np.ndarray, y: np.ndarray, line: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (m) as distance along ``line`` and signed offset from it (m, left +)."""
    origin, u = line
    d = np.stack([x, y], axis=1) - origin
    return d @ u, d @ np.array([-u[1], u[0]])


def same_as(rows: Sequence[dict[str, Any]], policies: Sequence[str], key: str) -> dict[str, str]:
    """Policies whose ``key`` means over PER equal an earlier policy's (to 1e-9): drawn
    on top of it, they would hide it, so the figures mark them (``label -> the other``)."""
    series = {label: [r[key]["mean"] for r in rows if r["policy"] == label] for label in policies}
    out: dict[str, str] = {}
    for i, label in enumerate(policies):
        for other in policies[:i]:
            a, b = np.array(series[label], float), np.array(series[other], float)
            if (
                a.shape == b.shape
                and len(a)
                and np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True)
            ):
                out[label] = out.get(other, other)
                break
    return out


# --- a sweep -----------------------------------------------------------------------------


def _per_colors(pers: Sequence[float]) -> dict[float, Any]:
    plt = _plt()
    cmap = plt.get_cmap("viridis")
    n = max(len(pers) - 1, 1)
    return {p: cmap(i / n) for i, p in enumerate(pers)}


def sweep_figures(result: SweepResult, out_dir: str | Path) -> list[Path]:
    """The paper's Figs 4–8 and a minimum-gap figure for a finished sweep."""
    out = Path(out_dir)
    cfg = result.config
    policies, pers = list(cfg.policies), list(cfg.pers)
    seed = cast(tuple[int, ...], cfg.seeds)[0]  # a tuple once built
    paths = [out / n for n in SWEEP_FIGURES]
    _trajectories(result, policies, pers, seed, paths[0])
    _over_time(
        result,
        policies,
        pers,
        seed,
        "speed_diff",
        "max − min speed over vehicles (m/s)",
        "Inter-vehicle speed difference",
        paths[1],
    )
    _over_time(
        result,
        policies,
        pers,
        seed,
        "max_error",
        "max platooning error |gap − desired| (m)",
        "Maximum platooning error",
        paths[2],
    )
    _vs_per(
        result.rows,
        policies,
        "mean_speed_difference_mps",
        "mean speed difference (m/s)",
        f"Mean speed difference vs PER ({cfg.scenario})",
        paths[3],
    )
    _vs_per(
        result.rows,
        policies,
        "p95_platooning_error_m",
        "95th percentile platooning error (m)",
        f"Platooning error vs PER ({cfg.scenario})",
        paths[4],
    )
    _min_gap(result, policies, pers, seed, paths[5])
    return paths


def _trajectories(result: SweepResult, policies, pers, seed, path: Path) -> None:
    """ENU trajectories; on a straight road (no lateral extent to see) each vehicle's
    position relative to the leader along the road over time instead, which shows how the
    spacing breathes."""
    plt = _plt()
    ncols = len(pers)
    fig, axes = plt.subplots(
        len(policies), ncols, figsize=(2.8 * ncols + 1, 2.6 * len(policies) + 0.6), squeeze=False
    )
    spans = [
        (np.nanmax(s["x"]) - np.nanmin(s["x"]), np.nanmax(s["y"]) - np.nanmin(s["y"]))
        for s in result.series.values()
    ]
    straight = all(dy < 0.05 * max(dx, 1e-9) for dx, dy in spans)
    for i, label in enumerate(policies):
        for j, per in enumerate(pers):
            ax = axes[i][j]
            s = result.series.get((label, per))
            if s is None:
                continue
            for vid, (x, y) in enumerate(zip(s["x"], s["y"])):
                if straight:
                    ax.plot(s["t"], x - s["x"][0], label=_vehicle_label(vid), lw=1)
                else:
                    ax.plot(x, y, label=_vehicle_label(vid), lw=1)
            ax.set_title(f"{label}, PER {per:.1f}", fontsize=9)
            ax.set_xlabel("time (s)" if straight else "east x (m)", fontsize=8)
            ax.set_ylabel("x − leader's x (m)" if straight else "north y (m)", fontsize=8)
            ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    what = "positions relative to the leader on the straight road" if straight else "trajectories"
    fig.suptitle(f"Vehicle {what} per PER ({result.config.scenario}, seed {seed})")
    _save(fig, path)


def _over_time(
    result: SweepResult, policies, pers, seed, key: str, ylabel: str, title: str, path: Path
) -> None:
    plt = _plt()
    colors = _per_colors(pers)
    fig, axes = plt.subplots(
        len(policies), 1, figsize=(9, 3.4 * len(policies) + 0.4), squeeze=False, sharex=True
    )
    for i, label in enumerate(policies):
        ax = axes[i][0]
        for per in pers:
            s = result.series.get((label, per))
            if s is not None:
                ax.plot(s["t"], s[key], color=colors[per], lw=1, label=f"PER {per:.1f}")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{title}: {label} (seed {seed})")
        ax.legend(fontsize=8, ncol=2)
    axes[-1][0].set_xlabel("time (s)")
    _save(fig, path)


_MARKERS = ("o", "s", "^", "D", "v", "P", "X")
_STYLES = ("-", "--", ":", "-.")


def _vs_per(rows, policies, key: str, ylabel: str, title: str, path: Path) -> None:
    """Each policy's mean ± std over seeds against PER; its own marker and line style,
    nudged sideways, and a policy equal to an earlier one says so in the legend."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.2))
    twins = same_as(rows, policies, key)
    pers = sorted({r["per"] for r in rows})
    step = min(np.diff(pers)) if len(pers) > 1 else 0.1
    for i, label in enumerate(policies):
        sel = [r for r in rows if r["policy"] == label]
        nudge = (i - (len(policies) - 1) / 2) * 0.06 * step
        x = [r["per"] + nudge for r in sel]
        mean = [r[key]["mean"] for r in sel]
        std = [r[key]["std"] for r in sel]
        note = f"; same as {twins[label]}" if label in twins else ""
        ax.errorbar(
            x,
            mean,
            yerr=std,
            marker=_MARKERS[i % len(_MARKERS)],
            ls=_STYLES[i % len(_STYLES)],
            capsize=3,
            label=f"{label} (mean ± std over seeds{note})",
        )
    ax.set_xlabel("packet error rate (PER)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    _save(fig, path)


def _min_gap(result: SweepResult, policies, pers, seed, path: Path) -> None:
    """Minimum gap vs PER for every policy, and the closest gap over time at the highest PER."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.2))
    worst = max(pers)
    limit = math.nan
    for label in policies:
        sel = [r for r in result.rows if r["policy"] == label]
        x = [r["per"] for r in sel]
        bars = a1.errorbar(
            x,
            [r["min_gap_m"]["mean"] for r in sel],
            yerr=[r["min_gap_m"]["std"] for r in sel],
            marker="o",
            capsize=3,
            label=f"{label}: mean ± std",
        )
        a1.plot(
            x,
            [r["min_gap_m"]["min"] for r in sel],
            "v",
            ms=6,
            color=bars[0].get_color(),
            label=f"{label}: worst seed",
        )
        s = result.series.get((label, worst))
        if s is not None:
            a2.plot(s["t"], s["closest_gap"], label=label)
            limit = s["collision_gap"]
    for ax in (a1, a2):
        if math.isfinite(limit) and limit > 0:
            ax.axhline(limit, color="red", ls=":", label="collision (sum of half lengths)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    a1.set_xlabel("packet error rate (PER)")
    a1.set_ylabel("minimum gap to predecessor (m)")
    a1.set_title(f"Minimum gap vs PER ({result.config.scenario})")
    a2.set_xlabel("time (s)")
    a2.set_ylabel("closest follower–predecessor gap (m)")
    a2.set_title(f"Closest gap over time, PER {worst:.1f}, seed {seed}")
    _save(fig, path)


def leaderboard_figure(rows: Sequence[dict[str, Any]], path: Path) -> Path:
    """The leaderboard's plot: per scenario (one row of axes), the p95 platooning error
    and the minimum gap of each policy under each link condition (x: condition and PER),
    the mean over seeds with its 95 % interval as error bars."""
    plt = _plt()
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    policies = list(dict.fromkeys(r["policy"] for r in rows))
    fig, axes = plt.subplots(len(scenarios), 2, figsize=(12, 3.2 * len(scenarios)), squeeze=False)
    for axrow, scenario in zip(axes, scenarios):
        sel = [r for r in rows if r["scenario"] == scenario]
        ticks = list(dict.fromkeys((r["loss"], r["per"]) for r in sel))
        for ax, key, ylabel in zip(
            axrow, ("p95_platooning_error_m", "min_gap_m"), ("p95 error (m)", "min gap (m)")
        ):
            for i, label in enumerate(policies):
                mine = {(r["loss"], r["per"]): r[key] for r in sel if r["policy"] == label}
                x = np.arange(len(ticks)) + (i - (len(policies) - 1) / 2) * 0.08
                mean = np.array([mine[t]["mean"] if t in mine else np.nan for t in ticks])
                lo = np.array([mine[t]["lo"] if t in mine else np.nan for t in ticks])
                hi = np.array([mine[t]["hi"] if t in mine else np.nan for t in ticks])
                err = np.nan_to_num(np.vstack([mean - lo, hi - mean]))
                ax.errorbar(
                    x,
                    mean,
                    yerr=err,
                    marker=_MARKERS[i % len(_MARKERS)],
                    ls="none",
                    capsize=3,
                    label=label,
                )
            if key.startswith("p95"):  # errors span orders of magnitude across scenarios
                ax.set_yscale("log")
            ax.set_xticks(np.arange(len(ticks)))
            ax.set_xticklabels(
                [f"{loss}\n{per:g}" for loss, per in ticks], fontsize=7, rotation=30, ha="right"
            )
            ax.set_ylabel(ylabel)
            ax.set_title(f"{scenario}: {ylabel} (mean, 95 % interval)", fontsize=9)
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    _save(fig, path)
    return path
