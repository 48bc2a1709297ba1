"""Run metrics as pure functions on arrays (DESIGN.md, Logs and metrics).

The inputs are a log's columns (``openconvoy.logs.Log``: column name -> numpy array), the
same for a simulator run and for merged per-vehicle logs of a vehicle run. Vehicles of a
vehicle run do not tick together, so time series that combine vehicles (speed difference,
gaps computed from positions) are taken on the union of all ticks, each vehicle's column
linearly interpolated inside its own time span (NaN outside it); on a simulator log, where
all vehicles share the ticks, this is exact.

Key names of ``compute_metrics`` are those of ``metrics.json``:
``p95_platooning_error_m``, ``mean_speed_difference_mps``, ``min_gap_m``, ``collisions``,
``string_stability``, ``delivery_ratio``; plus ``per_follower`` (vehicle id -> its own
values) and ``duration_s``. Missing values are NaN (``None`` in JSON).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

METRIC_KEYS: tuple[str, ...] = (
    "p95_platooning_error_m",
    "mean_speed_difference_mps",
    "min_gap_m",
    "collisions",
    "string_stability",
    "delivery_ratio",
)
"""The scalar metrics of ``metrics.json``, in DESIGN.md's order."""

Columns = Mapping[str, np.ndarray]


def vehicle_ids(log: Columns) -> list[int]:
    """Vehicle ids present in the log, ascending (0 = leader)."""
    return sorted(int(v) for v in np.unique(np.asarray(log["vehicle_id"])))


def _rows(log: Columns, vid: int) -> np.ndarray:
    """Row indices of vehicle ``vid``, in time order."""
    idx = np.flatnonzero(np.asarray(log["vehicle_id"]) == vid)
    return idx[np.argsort(np.asarray(log["t_s"], dtype=float)[idx], kind="stable")]


def time_grid(log: Columns) -> np.ndarray:
    """The union of all ticks (s), ascending."""
    return np.unique(np.asarray(log["t_s"], dtype=float))


def aligned(
    log: Columns, column: str, grid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``column`` per vehicle on a common time grid.

    Returns ``(t, values)`` where ``values[k, j]`` is vehicle ``vehicle_ids(log)[j]``'s
    value at ``t[k]``: its own sample when it has one at ``t[k]``, else linearly
    interpolated between its neighbouring samples, NaN outside its time span.
    """
    t = time_grid(log) if grid is None else np.asarray(grid, dtype=float)
    ids = vehicle_ids(log)
    out = np.full((len(t), len(ids)), np.nan)
    times = np.asarray(log["t_s"], dtype=float)
    col = np.asarray(log[column], dtype=float)
    for j, vid in enumerate(ids):
        r = _rows(log, vid)
        tv, yv = times[r], col[r]
        ok = np.isfinite(yv)
        tv, yv = tv[ok], yv[ok]
        if len(tv) == 0:
            continue
        inside = (t >= tv[0]) & (t <= tv[-1])
        out[inside, j] = np.interp(t[inside], tv, yv)
    return t, out


def follower_gaps(log: Columns) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each follower's gap to its immediate predecessor (m), centre to centre.

    Returns ``{vehicle_id: (t_s, gap_m)}`` at the follower's own ticks. When the log holds
    the predecessor's positions, the gap is the distance to them (interpolated at the
    follower's tick: vehicle logs tick on different clocks), which is the ground truth on
    vehicles too, where the logged ``gap_m`` is the member's estimate from received
    messages; the ``gap_m`` column fills the ticks outside the predecessor's time span.
    """
    ids = vehicle_ids(log)
    times = np.asarray(log["t_s"], dtype=float)
    x, y = np.asarray(log["x_m"], dtype=float), np.asarray(log["y_m"], dtype=float)
    logged = (
        np.asarray(log["gap_m"], dtype=float) if "gap_m" in log else np.full(len(times), np.nan)
    )
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for vid in ids:
        if vid == 0:
            continue
        r = _rows(log, vid)
        t = times[r]
        gap = logged[r].copy()
        if vid - 1 in ids:
            p = _rows(log, vid - 1)
            p = p[np.isfinite(x[p]) & np.isfinite(y[p])]
            tp = times[p]
            if len(tp):
                inside = (t >= tp[0]) & (t <= tp[-1]) & np.isfinite(x[r]) & np.isfinite(y[r])
                px = np.interp(t[inside], tp, x[p])
                py = np.interp(t[inside], tp, y[p])
                gap[inside] = np.hypot(x[r][inside] - px, y[r][inside] - py)
        out[vid] = (t, gap)
    return out


def platooning_errors(log: Columns) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each follower's platooning error |gap − desired gap| (m): ``{id: (t_s, error)}``."""
    desired_col = np.asarray(log["desired_gap_m"], dtype=float)
    out = {}
    for vid, (t, gap) in follower_gaps(log).items():
        desired = desired_col[_rows(log, vid)]
        out[vid] = (t, np.abs(gap - desired))
    return out


def _nanpercentile(values: np.ndarray, q: float) -> float:
    v = values[np.isfinite(values)]
    return float(np.percentile(v, q)) if len(v) else math.nan


def p95_platooning_error(log: Columns) -> tuple[float, dict[int, float]]:
    """95th percentile of the platooning error (m): pooled over all followers and ticks,
    and per follower."""
    errors = platooning_errors(log)
    per = {vid: _nanpercentile(e, 95.0) for vid, (_, e) in errors.items()}
    pooled = np.concatenate([e for _, e in errors.values()]) if errors else np.array([])
    return _nanpercentile(pooled, 95.0), per


def max_platooning_error_series(log: Columns) -> tuple[np.ndarray, np.ndarray]:
    """Largest platooning error over the followers at each tick (m): ``(t_s, error)``."""
    t = time_grid(log)
    errors = platooning_errors(log)
    if not errors:
        return t, np.full(len(t), np.nan)
    stack = np.full((len(t), len(errors)), np.nan)
    for j, (te, e) in enumerate(errors.values()):
        stack[np.searchsorted(t, te), j] = e
    with np.errstate(all="ignore"):
        return t, _nanmax_rows(stack)


def _nanmax_rows(a: np.ndarray) -> np.ndarray:
    out = np.full(a.shape[0], np.nan)
    ok = np.isfinite(a).any(axis=1)
    out[ok] = np.nanmax(a[ok], axis=1)
    return out


def speed_difference_series(log: Columns) -> tuple[np.ndarray, np.ndarray]:
    """Max − min speed over all vehicles at each tick (m/s): ``(t_s, difference)``.
    Ticks where fewer than two vehicles have a speed are NaN."""
    t, v = aligned(log, "speed_mps")
    n = np.isfinite(v).sum(axis=1)
    diff = np.full(len(t), np.nan)
    ok = n >= 2
    diff[ok] = np.nanmax(v[ok], axis=1) - np.nanmin(v[ok], axis=1)
    return t, diff


def mean_speed_difference(log: Columns) -> float:
    """Mean over the run of the max − min speed over all vehicles (m/s)."""
    _, d = speed_difference_series(log)
    d = d[np.isfinite(d)]
    return float(d.mean()) if len(d) else math.nan


def min_gaps(log: Columns) -> dict[int, float]:
    """Smallest gap of each follower to its predecessor over the run (m)."""
    out = {}
    for vid, (_, gap) in follower_gaps(log).items():
        g = gap[np.isfinite(gap)]
        out[vid] = float(g.min()) if len(g) else math.nan
    return out


def collisions(log: Columns, lengths: Mapping[int, float]) -> tuple[int, dict[int, bool]]:
    """Follower–predecessor pairs whose gap fell below the sum of their half lengths.

    ``lengths`` maps vehicle id to length (m). Returns the count of such pairs and, per
    follower, whether its pair collided.
    """
    per: dict[int, bool] = {}
    for vid, (_, gap) in follower_gaps(log).items():
        limit = 0.5 * (lengths.get(vid, 0.0) + lengths.get(vid - 1, 0.0))
        g = gap[np.isfinite(gap)]
        per[vid] = bool(len(g) and g.min() < limit)
    return sum(per.values()), per


def string_stability(log: Columns) -> tuple[float, dict[int, float]]:
    """Ratio of each follower's peak platooning error to its predecessor's (< 1: errors
    shrink along the string). Per follower from the second on; the scalar is the largest
    ratio (the string is stable when every ratio is below 1). NaN with one follower."""
    errors = platooning_errors(log)
    peaks = {
        vid: float(np.nanmax(e)) if np.isfinite(e).any() else math.nan
        for vid, (_, e) in errors.items()
    }
    ratios: dict[int, float] = {}
    for vid, peak in peaks.items():
        prev = peaks.get(vid - 1)
        if prev is None:
            continue
        ratios[vid] = peak / prev if prev > 0 else math.nan
    finite = [r for r in ratios.values() if math.isfinite(r)]
    return (max(finite) if finite else math.nan), ratios


def delivery_ratio(log: Columns) -> float:
    """Messages received / (received + lost), over all followers' final counters.

    ``msgs_received`` and ``msgs_lost`` are cumulative per vehicle (the last row of each
    vehicle holds its totals). NaN when nothing was offered.
    """
    ids = vehicle_ids(log)
    received = lost = 0
    rec_col = np.asarray(log["msgs_received"])
    lost_col = np.asarray(log["msgs_lost"])
    for vid in ids:
        r = _rows(log, vid)
        rec, los = rec_col[r], lost_col[r]
        rec, los = rec[rec >= 0], los[los >= 0]  # -1 = not logged
        received += int(rec.max()) if len(rec) else 0
        lost += int(los.max()) if len(los) else 0
    total = received + lost
    return received / total if total else math.nan


def delivery_per_follower(log: Columns) -> dict[int, float]:
    """Each follower's delivery ratio, received / (received + lost), from its final
    counters; followers whose link applies no loss (counters -1, "not logged") and those
    offered nothing are left out, as is the leader."""
    out: dict[int, float] = {}
    rec_col = np.asarray(log["msgs_received"])
    lost_col = np.asarray(log["msgs_lost"])
    for vid in vehicle_ids(log):
        if vid == 0:
            continue
        r = _rows(log, vid)
        rec, los = rec_col[r], lost_col[r]
        rec, los = rec[rec >= 0], los[los >= 0]  # -1 = not logged
        received = int(rec.max()) if len(rec) else 0
        total = received + (int(los.max()) if len(los) else 0)
        if total:
            out[vid] = received / total
    return out


def compute_metrics(log: Columns, lengths: Mapping[int, float] | None = None) -> dict[str, Any]:
    """All metrics of a run, with ``metrics.json``'s key names.

    ``lengths`` (vehicle id -> length, m) sets the collision thresholds; when omitted, a
    ``length_m`` log column is used if present, else lengths count as 0 (a collision is then
    only a gap of zero or less: pass the lengths whenever they are known).
    """
    if lengths is None:
        lengths = lengths_from_log(log)
    p95, p95_per = p95_platooning_error(log)
    n_coll, coll_per = collisions(log, lengths)
    ss, ss_per = string_stability(log)
    gaps = min_gaps(log)
    t = np.asarray(log["t_s"], dtype=float)
    delivery = delivery_per_follower(log)
    per_follower: dict[str, dict[str, Any]] = {}
    for vid in sorted(p95_per):
        per_follower[str(vid)] = {
            "p95_platooning_error_m": p95_per[vid],
            "min_gap_m": gaps.get(vid, math.nan),
            "collided": coll_per.get(vid, False),
            "string_stability": ss_per.get(vid, math.nan),
        }
        if vid in delivery:
            per_follower[str(vid)]["delivery_ratio"] = delivery[vid]
    finite_gaps = [g for g in gaps.values() if math.isfinite(g)]
    return {
        "p95_platooning_error_m": p95,
        "mean_speed_difference_mps": mean_speed_difference(log),
        "min_gap_m": min(finite_gaps) if finite_gaps else math.nan,
        "collisions": n_coll,
        "string_stability": ss,
        "delivery_ratio": delivery_ratio(log),
        "duration_s": float(t.max() - t.min()) if len(t) else 0.0,
        "per_follower": per_follower,
    }


def lengths_from_log(log: Columns) -> dict[int, float]:
    """Vehicle lengths (m) from a ``length_m`` column, if the log has one; else empty."""
    if "length_m" not in log:
        return {}
    out = {}
    col = np.asarray(log["length_m"], dtype=float)
    for vid in vehicle_ids(log):
        v = col[_rows(log, vid)]
        v = v[np.isfinite(v)]
        if len(v):
            out[vid] = float(v[0])
    return out


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf floats replaced by ``None`` (JSON has no NaN), recursively;
    numpy scalars become Python numbers."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        return f if math.isfinite(f) else None
    return value


# --- traffic metrics (highway scenarios, issue 13) ------------------------------------------

TRAFFIC_METRIC_KEYS: tuple[str, ...] = (
    "min_ttc_s",
    "min_gap_ahead_m",
    "gap_restore_time_s",
    "string_stability_after_disturbance",
    "traffic_collisions",
)
"""The traffic metrics of ``metrics.json`` (runs whose log has the ``ahead_*`` columns of
``openconvoy.envs.traffic.env.TRAFFIC_LOG_COLUMNS``); definitions in ``traffic_metrics``."""

RESTORE_TOLERANCE_M = 1.0
RESTORE_TOLERANCE_FRACTION = 0.1


def has_traffic_columns(log: Columns) -> bool:
    """Does the log carry the traffic columns (a highway run)?"""
    return all(
        c in log for c in ("ahead_gap_m", "ahead_closing_mps", "ahead_length_m", "ahead_traffic")
    )


def time_to_collision(
    log: Columns, lengths: Mapping[int, float]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each vehicle's time to collision with the vehicle in its path ahead (s):
    bumper-to-bumper gap (centre gap less the two half lengths) over the closing speed,
    where closing; inf where the gap opens or nothing is ahead. ``{id: (t_s, ttc_s)}``."""
    out = {}
    gap_c = np.asarray(log["ahead_gap_m"], dtype=float)
    closing_c = np.asarray(log["ahead_closing_mps"], dtype=float)
    other_c = np.asarray(log["ahead_length_m"], dtype=float)
    times = np.asarray(log["t_s"], dtype=float)
    for vid in vehicle_ids(log):
        r = _rows(log, vid)
        bumper = gap_c[r] - 0.5 * (lengths.get(vid, 0.0) + np.nan_to_num(other_c[r]))
        closing = closing_c[r]
        ttc = np.full(len(r), math.inf)
        ok = np.isfinite(bumper) & np.isfinite(closing) & (closing > 0.0)
        ttc[ok] = np.maximum(bumper[ok], 0.0) / closing[ok]
        out[vid] = (times[r], ttc)
    return out


def min_time_to_collision(
    log: Columns, lengths: Mapping[int, float]
) -> tuple[float, dict[int, float]]:
    """Smallest time to collision (s) over the run: overall and per vehicle (inf: never closing)."""
    per = {
        vid: float(ttc.min()) if len(ttc) else math.inf
        for vid, (_, ttc) in time_to_collision(log, lengths).items()
    }
    return (min(per.values()) if per else math.inf), per


def min_gap_ahead(log: Columns) -> tuple[float, dict[int, float]]:
    """Smallest centre-to-centre distance (m) to the vehicle in the path ahead, convoy or
    traffic: overall and per vehicle (NaN when nothing was ever ahead)."""
    col = np.asarray(log["ahead_gap_m"], dtype=float)
    per = {}
    for vid in vehicle_ids(log):
        g = col[_rows(log, vid)]
        g = g[np.isfinite(g)]
        per[vid] = float(g.min()) if len(g) else math.nan
    finite = [g for g in per.values() if math.isfinite(g)]
    return (min(finite) if finite else math.nan), per


def intrusions(log: Columns) -> dict[int, list[tuple[float, float]]]:
    """Per follower, the time intervals ``(start_s, end_s)`` during which the vehicle in its
    path ahead was traffic (a car without V2V in its gap): ``end_s`` is the first tick
    without it (or the last tick if it stayed)."""
    col = np.asarray(log["ahead_traffic"], dtype=float)
    times = np.asarray(log["t_s"], dtype=float)
    out: dict[int, list[tuple[float, float]]] = {}
    for vid in vehicle_ids(log):
        if vid == 0:
            continue
        r = _rows(log, vid)
        t, flag = times[r], col[r] == 1.0
        spans = []
        k = 0
        while k < len(t):
            if flag[k]:
                j = k
                while j < len(t) and flag[j]:
                    j += 1
                spans.append((float(t[k]), float(t[min(j, len(t) - 1)])))
                k = j
            else:
                k += 1
        out[vid] = spans
    return out


def gap_restore_times(log: Columns) -> dict[int, float]:
    """Per disturbed follower, the time (s) from the end of its last intrusion until its
    platooning error |gap − desired gap| comes within ``max(1 m, 10 % of the desired
    gap)`` and stays there to the end of the run; inf if it never does. Followers
    without intrusions are left out."""
    errors = platooning_errors(log)
    desired_col = np.asarray(log["desired_gap_m"], dtype=float)
    out = {}
    for vid, spans in intrusions(log).items():
        if not spans:
            continue
        end = spans[-1][1]
        t, err = errors[vid]
        desired = desired_col[_rows(log, vid)]
        tol = np.maximum(RESTORE_TOLERANCE_M, RESTORE_TOLERANCE_FRACTION * np.nan_to_num(desired))
        after = t >= end
        bad = after & ~(err <= tol)
        if spans[-1][1] >= t[-1] or not after.any() or bad[after][-1]:  # never left, never back
            out[vid] = math.inf
            continue
        last_bad = np.flatnonzero(bad)
        out[vid] = float(t[last_bad[-1] + 1] - end) if len(last_bad) else 0.0
    return out


def string_stability_after(log: Columns, t0: float) -> tuple[float, dict[int, float]]:
    """``string_stability`` on the part of the log from ``t0`` (s) on."""
    keep = np.asarray(log["t_s"], dtype=float) >= t0
    return string_stability({k: np.asarray(v)[keep] for k, v in log.items()})


def traffic_collisions(log: Columns) -> int:
    """Convoy vehicles that touched traffic (or a road obstacle) during the run."""
    if "traffic_collision" not in log:
        return 0
    col = np.asarray(log["traffic_collision"], dtype=float)
    return sum(
        bool(np.nanmax(col[_rows(log, vid)], initial=0.0) >= 1.0) for vid in vehicle_ids(log)
    )


def traffic_metrics(log: Columns, lengths: Mapping[int, float]) -> dict[str, Any]:
    """The traffic metrics (``TRAFFIC_METRIC_KEYS``) of a highway run:

    - ``min_ttc_s``: smallest time to collision of any convoy vehicle with the vehicle in
      its path ahead (bumper gap / closing speed; inf = never closing);
    - ``min_gap_ahead_m``: smallest centre-to-centre distance of any convoy vehicle to the
      vehicle in its path ahead, convoy or traffic;
    - ``gap_restore_time_s``: the longest ``gap_restore_times`` over the disturbed
      followers (NaN: no intrusion; inf: a gap never restored);
    - ``string_stability_after_disturbance``: ``string_stability`` from the first intrusion
      on (NaN without one);
    - ``traffic_collisions``: ``traffic_collisions``.

    ``gap_restored`` says whether every disturbed follower restored its gap (None without a
    disturbance) and ``disturbance_s`` when the first intrusion began.
    """
    ttc, ttc_per = min_time_to_collision(log, lengths)
    gap, _ = min_gap_ahead(log)
    restore = gap_restore_times(log)
    starts = [s[0][0] for s in intrusions(log).values() if s]
    t0 = min(starts) if starts else math.nan
    ss = string_stability_after(log, t0)[0] if starts else math.nan
    return {
        "min_ttc_s": ttc,
        "min_gap_ahead_m": gap,
        "gap_restore_time_s": max(restore.values()) if restore else math.nan,
        "string_stability_after_disturbance": ss,
        "traffic_collisions": traffic_collisions(log),
        "gap_restored": all(math.isfinite(v) for v in restore.values()) if restore else None,
        "disturbance_s": t0,
        "restore_time_per_follower_s": {str(k): v for k, v in restore.items()},
    }
