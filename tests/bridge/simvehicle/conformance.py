"""Shared analysis for the conformance tests: one recording of real firmware and its replay
into the simulated vehicle, measured by the same functions (``firmware`` and ``sim``)."""

from __future__ import annotations

import bisect
import functools
import math
from pathlib import Path
from typing import Any

from openconvoy.bridge.simvehicle.replay import boot_time, load_recording, replay

DATA = Path(__file__).resolve().parents[2] / "data"  # tests/data: see its README
Record = dict[str, Any]
RX_TYPES = {
    "GLOBAL_POSITION_INT",
    "ATTITUDE",
    "SERVO_OUTPUT_RAW",
    "HEARTBEAT",
    "STATUSTEXT",
    "COMMAND_ACK",
    "HIL_STATE_QUATERNION",
}
"""What the analyses read; the rest of each recording (and of each replay) is skipped."""


@functools.cache
def sides(folder: str, name: str) -> dict[str, Any]:
    """``{"firmware": records, "sim": records, "boot": {side: t_boot}}`` for one recording."""
    meta, recs = load_recording(DATA / folder / f"{name}.jsonl.gz", RX_TYPES)
    t_boot = boot_time(meta, recs)
    return {
        "firmware": recs,
        "sim": replay(meta, recs, rx_types=RX_TYPES),
        "boot": t_boot,
        "meta": meta,
    }


def phase(recs: list[Record], name: str, k: int = 0) -> tuple[float, float, dict[str, Any]]:
    """(start, end, fields) of the k-th phase mark called ``name`` (end = next mark)."""
    marks = [r for r in recs if r["dir"] == "mark"]
    hits = [i for i, r in enumerate(marks) if r["fields"]["name"] == name]
    i = hits[k]
    end = marks[i + 1]["t"] if i + 1 < len(marks) else math.inf
    return marks[i]["t"], end, marks[i]["fields"]


_INDEX: dict[int, dict[tuple[str, str | None], tuple[list[float], list[Record]]]] = {}


def rx(
    recs: list[Record],
    kind: str,
    t0: float = -math.inf,
    t1: float = math.inf,
    link: str | None = None,
) -> list[Record]:
    """Received messages of one type (and link) with t0 <= t < t1, from a per-recording
    index (the recordings are cached, so their identity is stable)."""
    index = _INDEX.get(id(recs))
    if index is None:
        index = {}
        for r in recs:
            if r["dir"] == "rx":
                index.setdefault((r["type"], r.get("link")), ([], []))[1].append(r)
        for times, rows in index.values():
            rows.sort(key=lambda r: r["t"])
            times.extend(r["t"] for r in rows)
        _INDEX[id(recs)] = index
    times, rows = index.get((kind, link), ([], []))
    return rows[bisect.bisect_left(times, t0) : bisect.bisect_left(times, t1)]


def motion(recs: list[Record], t0: float, t1: float) -> list[tuple[float, float, float, float]]:
    """(t, signed speed m/s, heading deg, course deg) from GLOBAL_POSITION_INT."""
    out = []
    for r in rx(recs, "GLOBAL_POSITION_INT", t0, t1):
        f = r["fields"]
        vn, ve, h = f["vx"] / 100.0, f["vy"] / 100.0, math.radians(f["hdg"] / 100.0)
        out.append(
            (
                r["t"],
                vn * math.cos(h) + ve * math.sin(h),
                f["hdg"] / 100.0,
                math.degrees(math.atan2(ve, vn)) % 360.0,
            )
        )
    return out


def yaw_series(recs: list[Record], t0: float, t1: float) -> list[tuple[float, float, float]]:
    """(t, yaw deg 0..360, yaw rate deg/s) from ATTITUDE."""
    return [
        (r["t"], math.degrees(r["fields"]["yaw"]) % 360.0, math.degrees(r["fields"]["yawspeed"]))
        for r in rx(recs, "ATTITUDE", t0, t1)
    ]


def servos(recs: list[Record], t0: float, t1: float) -> list[tuple[float, int, int]]:
    """(t, steering µs, throttle µs) from SERVO_OUTPUT_RAW."""
    return [
        (r["t"], r["fields"]["servo1_raw"], r["fields"]["servo3_raw"])
        for r in rx(recs, "SERVO_OUTPUT_RAW", t0, t1)
    ]


def texts(
    recs: list[Record], t0: float = -math.inf, t1: float = math.inf
) -> list[tuple[float, str]]:
    """STATUSTEXTs with chunks joined."""
    out: list[tuple[float, str]] = []
    pending: dict[int, list[Any]] = {}
    for r in rx(recs, "STATUSTEXT", t0, t1):
        f = r["fields"]
        if f.get("id", 0) == 0:
            out.append((r["t"], f["text"]))
            continue
        entry = pending.setdefault(f["id"], [r["t"], ""])
        entry[1] += f["text"]
        if len(f["text"]) < 50:
            out.append((entry[0], entry[1]))
            del pending[f["id"]]
    return out


def acks(
    recs: list[Record], command: int, t0: float = -math.inf, t1: float = math.inf
) -> list[tuple[float, int]]:
    return [
        (r["t"], r["fields"]["result"])
        for r in rx(recs, "COMMAND_ACK", t0, t1)
        if r["fields"]["command"] == command
    ]


def heartbeats(
    recs: list[Record], t0: float = -math.inf, t1: float = math.inf
) -> list[tuple[float, int, int, int]]:
    """(t, custom_mode, base_mode, system_status)."""
    return [
        (r["t"], r["fields"]["custom_mode"], r["fields"]["base_mode"], r["fields"]["system_status"])
        for r in rx(recs, "HEARTBEAT", t0, t1)
    ]


def angle_diff(a: float, b: float) -> float:
    """a − b wrapped to (−180, 180] degrees."""
    return (a - b + 180.0) % 360.0 - 180.0


def mean(values: list[float]) -> float:
    return sum(values) / len(values)


def circular_mean(degrees_: list[float]) -> float:
    s = sum(math.sin(math.radians(d)) for d in degrees_)
    c = sum(math.cos(math.radians(d)) for d in degrees_)
    return math.degrees(math.atan2(s, c)) % 360.0


def step_metrics(
    samples: list[tuple[float, float]], t0: float, v0: float, v1: float
) -> dict[str, float]:
    """Rise (t10, t90), peak overshoot past v1, accel 20-80 % and the last value, of a
    speed step v0 -> v1 starting at t0, from (t, v) samples."""
    step = v1 - v0
    rel = [(t - t0, (v - v0) / step, v) for t, v in samples if t >= t0]

    def first(frac: float) -> float:
        return next((t for t, r, _ in rel if r >= frac), math.nan)

    peak = max(r for _, r, _ in rel)
    t20, t80 = first(0.2), first(0.8)
    return {
        "dead": next((t for t, r, _ in rel if abs(r * step) >= 0.05), math.nan),
        "t10": first(0.1),
        "t90": first(0.9),
        "overshoot": (peak - 1.0) * abs(step),
        "accel": 0.6 * step / (t80 - t20) if t80 > t20 else math.nan,
        "end": rel[-1][2],
    }
