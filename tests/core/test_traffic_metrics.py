"""Traffic metrics as pure functions on log columns (synthetic logs with known answers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.core import metrics as mt

DT = 0.5


def _log(n_ticks: int = 41) -> dict[str, np.ndarray]:
    """Leader + 2 followers at 20 m/s, 20 m apart (desired 20 m); follower 1 has a car cut
    in at 5 s (8 m ahead, closing at 2 m/s) until 8 s; its gap is 30 m from 8 s and
    closes 1 m per tick after 10 s to 20 m at 15 s."""
    t = np.arange(n_ticks) * DT
    rows: dict[str, list] = {
        k: []
        for k in (
            "t_s",
            "vehicle_id",
            "x_m",
            "y_m",
            "desired_gap_m",
            "gap_m",
            "ahead_gap_m",
            "ahead_closing_mps",
            "ahead_length_m",
            "ahead_traffic",
            "traffic_collision",
        )
    }
    for tk in t:
        gap1 = 20.0 if tk < 8.0 else (30.0 if tk < 10.0 else max(20.0, 30.0 - (tk - 10.0) * 2.0))
        xs = [20.0 * tk, 20.0 * tk - gap1, 20.0 * tk - gap1 - 20.0]
        for vid in range(3):
            cut = vid == 1 and 5.0 <= tk < 8.0
            rows["t_s"].append(tk)
            rows["vehicle_id"].append(vid)
            rows["x_m"].append(xs[vid])
            rows["y_m"].append(0.0)
            rows["desired_gap_m"].append(math.nan if vid == 0 else 20.0)
            rows["gap_m"].append(math.nan if vid == 0 else xs[vid - 1] - xs[vid])
            rows["ahead_gap_m"].append(
                math.nan if vid == 0 else (8.0 if cut else xs[vid - 1] - xs[vid])
            )
            rows["ahead_closing_mps"].append(math.nan if vid == 0 else (2.0 if cut else 0.0))
            rows["ahead_length_m"].append(math.nan if vid == 0 else (5.0 if cut else 4.8))
            rows["ahead_traffic"].append(math.nan if vid == 0 else (1.0 if cut else 0.0))
            rows["traffic_collision"].append(0.0)
    return {k: np.array(v, dtype=float if k != "vehicle_id" else np.int64) for k, v in rows.items()}


LENGTHS = {0: 4.8, 1: 4.8, 2: 4.8}


def test_ttc_gap_ahead_and_intrusions() -> None:
    log = _log()
    assert mt.has_traffic_columns(log)
    ttc, per = mt.min_time_to_collision(log, LENGTHS)
    # 8 m centre to centre, 4.9 m of half lengths: 3.1 m between bumpers at 2 m/s.
    assert ttc == pytest.approx(3.1 / 2.0) and per[1] == ttc and per[2] == math.inf
    gap, per_gap = mt.min_gap_ahead(log)
    assert gap == 8.0 and per_gap[2] == 20.0 and math.isnan(per_gap[0])
    assert mt.intrusions(log) == {1: [(5.0, 8.0)], 2: []}


def test_restore_time_and_string_stability_after() -> None:
    log = _log()
    # Tolerance max(1 m, 2 m): within it from the tick where the gap is 22 m (14 s),
    # 6 s after the intruder left at 8 s.
    assert mt.gap_restore_times(log) == {1: pytest.approx(6.0)}
    m = mt.traffic_metrics(log, LENGTHS)
    assert m["gap_restore_time_s"] == pytest.approx(6.0) and m["gap_restored"] is True
    assert m["disturbance_s"] == 5.0 and m["traffic_collisions"] == 0
    # Follower 2 kept 20 m to follower 1 all along: its error is 0, the ratio 0.
    assert m["string_stability_after_disturbance"] == pytest.approx(0.0)
    # Cut the log before the gap closes: never restored.
    short = {k: v[: 3 * 25] for k, v in log.items()}
    assert mt.gap_restore_times(short) == {1: math.inf}
    assert mt.traffic_metrics(short, LENGTHS)["gap_restored"] is False


def test_traffic_collisions_count_vehicles() -> None:
    log = _log()
    log["traffic_collision"][(log["vehicle_id"] == 2) & (log["t_s"] >= 19.0)] = 1.0
    assert mt.traffic_collisions(log) == 1
    no_traffic = {
        k: v for k, v in log.items() if not k.startswith("ahead") and k != "traffic_collision"
    }
    assert not mt.has_traffic_columns(no_traffic) and mt.traffic_collisions(no_traffic) == 0
