"""Two runs or two sweeps side by side (``openconvoy compare A B``).

A side is a run (a log file, a run directory of one or per-vehicle logs: sim or vehicle),
whose metrics are recomputed from its logs, or a sweep (a directory with
``summary.json``, or that file), whose rows are matched by (policy, PER) — or by PER alone
when each side has a single policy, so a ``paper`` sweep compares with a
``paper+ladder`` one. Differences are B − A. What one side has and the other lacks (a
policy, a PER, a follower) is listed as left out, never dropped silently.

A vehicle run (deploy logs with their ``vehicle_N.json``) compared with a sim run is cut to
the scenario's window: from the leader's start for the sim's duration (``load_pair``), so
the armed wait before and the braking after a drive do not count on one side only. Two runs
end with a verdict line (``calibration.verdict``): p95 platooning error, string stability and
mean speed difference as ratios B / A, the calibration workflow's test (docs/calibration.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openconvoy.core import metrics as mt
from openconvoy.core.errors import InputFileError


@dataclass
class Side:
    """One side of a comparison: ``kind`` ``run`` (``metrics``) or ``sweep`` (``rows``)."""

    path: Path
    kind: str
    metrics: dict[str, Any] | None = None
    rows: list[dict[str, Any]] | None = None
    note: str = ""


def load_side(path: str | Path, lengths: Mapping[int, float] | None = None) -> Side:
    """Read a run or a sweep; ``lengths`` (vehicle id -> m) for logs without ``length_m``."""
    from openconvoy.experiments.sweep import read_summary
    from openconvoy.logs import read_log

    p = Path(path)
    if (p.is_dir() and (p / "summary.json").is_file()) or p.name == "summary.json":
        return Side(p, "sweep", rows=read_summary(p))
    log = read_log(p)
    return Side(p, "run", metrics=mt.compute_metrics(log, lengths))


def load_pair(
    a: str | Path, b: str | Path, lengths: Mapping[int, float] | None = None
) -> tuple[Side, Side]:
    """Both sides; a vehicle run facing a sim run is cut to the sim's scenario window."""
    from openconvoy.experiments.calibration import scenario_start, windowed_metrics

    sa, sb = load_side(a, lengths), load_side(b, lengths)
    if sa.kind == sb.kind == "run":
        starts = scenario_start(a), scenario_start(b)
        if (starts[0] is None) != (starts[1] is None):
            sim, vehicle = (sb, sa) if starts[0] is not None else (sa, sb)
            assert sim.metrics is not None
            vehicle.metrics, vehicle.note = windowed_metrics(
                vehicle.path, float(sim.metrics["duration_s"]), dict(lengths or {}) or None
            )
            sim.note = "whole run"
    return sa, sb


def _diff(a: float, b: float) -> float:
    return b - a if math.isfinite(a) and math.isfinite(b) else math.nan


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def compare(a: Side, b: Side) -> dict[str, Any]:
    """The comparison as data: runs give ``{"metrics": {key: {a, b, diff}}}``; sweeps give
    ``{"rows": [{"policy_a", "policy_b", "per", key: {a, b, diff}}]}`` (means over seeds)."""
    if a.kind != b.kind:
        raise InputFileError(f"cannot compare a {a.kind} ({a.path}) with a {b.kind} ({b.path})")
    if a.kind == "run":
        assert a.metrics is not None and b.metrics is not None
        out = {k: _triple(_num(a.metrics[k]), _num(b.metrics[k])) for k in mt.METRIC_KEYS}
        followers = sorted(set(a.metrics["per_follower"]) & set(b.metrics["per_follower"]), key=int)
        per_f = {
            f: {
                "p95_platooning_error_m": _triple(
                    _num(a.metrics["per_follower"][f]["p95_platooning_error_m"]),
                    _num(b.metrics["per_follower"][f]["p95_platooning_error_m"]),
                )
            }
            for f in followers
        }
        only = {
            side: sorted(set(mine["per_follower"]) - set(other["per_follower"]), key=int)
            for side, mine, other in (("a", a.metrics, b.metrics), ("b", b.metrics, a.metrics))
        }
        from openconvoy.experiments.calibration import verdict

        return {
            "kind": "run",
            "a": str(a.path),
            "b": str(b.path),
            "window_a": a.note,
            "window_b": b.note,
            "metrics": out,
            "per_follower": per_f,
            "left_out": {side: [f"follower {f}" for f in fs] for side, fs in only.items()},
            "verdict": verdict(a.metrics, b.metrics),
        }
    assert a.rows is not None and b.rows is not None
    pol_a = {r["policy"] for r in a.rows}
    pol_b = {r["policy"] for r in b.rows}
    by_per_only = len(pol_a) == 1 and len(pol_b) == 1
    index_b = {(None if by_per_only else r["policy"], r["per"]): r for r in b.rows}
    rows = []
    matched: set[tuple[str | None, float]] = set()
    left_a: list[str] = []
    for ra in a.rows:
        key = (None if by_per_only else ra["policy"], ra["per"])
        rb = index_b.get(key)
        if rb is None:
            left_a.append(f"{ra['policy']} at PER {ra['per']:.2f}")
            continue
        matched.add(key)
        row: dict[str, Any] = {"per": ra["per"], "policy_a": ra["policy"], "policy_b": rb["policy"]}
        for k in mt.METRIC_KEYS:
            row[k] = _triple(ra[k]["mean"], rb[k]["mean"])
        rows.append(row)
    if not rows:
        raise InputFileError(f"{a.path} and {b.path} have no (policy, PER) row in common")
    left_b = [
        f"{r['policy']} at PER {r['per']:.2f}" for k, r in index_b.items() if k not in matched
    ]
    return {
        "kind": "sweep",
        "a": str(a.path),
        "b": str(b.path),
        "rows": rows,
        "left_out": {"a": left_a, "b": left_b},
    }


def _triple(a: float, b: float) -> dict[str, float]:
    return {"a": a, "b": b, "diff": _diff(a, b)}


def _f(v: float) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.4g}"


def format_comparison(result: dict[str, Any]) -> str:
    """A plain-text table of ``compare``'s result, then what it left out (one line a side)."""
    table = _table(result)
    left = result.get("left_out", {})
    for side, other in (("a", "B"), ("b", "A")):
        if left.get(side):
            table += f"\nleft out, only in {side.upper()} (nothing to match in {other}): "
            table += ", ".join(left[side])
    return table


def _table(result: dict[str, Any]) -> str:
    lines = [f"A: {result['a']}", f"B: {result['b']}"]
    if result["kind"] == "run":
        from openconvoy.experiments.calibration import format_verdict

        for side in ("a", "b"):
            if result.get(f"window_{side}"):
                lines.append(f"{side.upper()} window: {result[f'window_{side}']}")
        lines.append(f"{'metric':<28}{'A':>12}{'B':>12}{'B - A':>12}")
        for k, v in result["metrics"].items():
            lines.append(f"{k:<28}{_f(v['a']):>12}{_f(v['b']):>12}{_f(v['diff']):>12}")
        for f, v in result["per_follower"].items():
            t = v["p95_platooning_error_m"]
            name = f"  follower {f} p95 error (m)"
            lines.append(f"{name:<28}{_f(t['a']):>12}{_f(t['b']):>12}{_f(t['diff']):>12}")
        lines.append(format_verdict(result["verdict"]))
        return "\n".join(lines)
    short = {
        "p95_platooning_error_m": "p95 err (m)",
        "mean_speed_difference_mps": "dv (m/s)",
        "min_gap_m": "min gap (m)",
        "collisions": "collisions",
        "string_stability": "string",
        "delivery_ratio": "delivery",
    }
    lines.append("means over seeds, A / B / B - A")
    header = f"{'policy A | B':<30}{'PER':>5}" + "".join(f"{short[k]:>28}" for k in mt.METRIC_KEYS)
    lines.append(header)
    for r in result["rows"]:
        pols = (
            r["policy_a"]
            if r["policy_a"] == r["policy_b"]
            else f"{r['policy_a']} | {r['policy_b']}"
        )
        cells = "".join(
            f"{_f(r[k]['a']) + ' / ' + _f(r[k]['b']) + ' / ' + _f(r[k]['diff']):>28}"
            for k in mt.METRIC_KEYS
        )
        lines.append(f"{pols:<30}{r['per']:>5.2f}{cells}")
    return "\n".join(lines)
