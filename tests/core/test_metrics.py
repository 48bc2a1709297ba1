"""Metrics on hand-built logs whose answers are known exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.core import metrics as m


def make_log(t, xs, speeds, desired=15.0, gap_logged=True, received=None, lost=None):
    """A straight-road log: ``xs[i]``, ``speeds[i]`` are vehicle i's arrays over ``t``."""
    n = len(xs)
    cols: dict[str, list] = {
        c: []
        for c in (
            "t_s",
            "vehicle_id",
            "x_m",
            "y_m",
            "speed_mps",
            "gap_m",
            "desired_gap_m",
            "msgs_received",
            "msgs_lost",
        )
    }
    for k, tk in enumerate(t):
        for i in range(n):
            cols["t_s"].append(tk)
            cols["vehicle_id"].append(i)
            cols["x_m"].append(xs[i][k])
            cols["y_m"].append(0.0)
            cols["speed_mps"].append(speeds[i][k])
            gap = xs[i - 1][k] - xs[i][k] if i > 0 and gap_logged else math.nan
            cols["gap_m"].append(gap)
            cols["desired_gap_m"].append(desired if i > 0 else math.nan)
            cols["msgs_received"].append(received[i][k] if received else 0)
            cols["msgs_lost"].append(lost[i][k] if lost else 0)
    out = {k: np.asarray(v, dtype=float) for k, v in cols.items()}
    for k in ("vehicle_id", "msgs_received", "msgs_lost"):
        out[k] = out[k].astype(np.int64)
    return out


T = np.arange(0.0, 10.0, 0.5)  # 20 ticks


def test_platooning_error_pooled_and_per_follower():
    lead = 100.0 + T
    f1 = lead - 15.0 - 1.0  # 1 m too far back throughout
    f2 = f1 - 15.0 + np.where(T >= 5.0, 2.0, 0.0)  # 2 m too close in the second half
    log = make_log(T, [lead, f1, f2], [np.ones_like(T)] * 3)
    pooled, per = m.p95_platooning_error(log)
    assert per[1] == pytest.approx(1.0)
    assert per[2] == pytest.approx(2.0)
    # Pooled: 20 ones, 10 zeros, 10 twos -> the 95th percentile is 2.
    assert pooled == pytest.approx(2.0)
    _, series = m.max_platooning_error_series(log)
    assert series[0] == pytest.approx(1.0) and series[-1] == pytest.approx(2.0)


def test_speed_difference_and_min_gap():
    lead = 100.0 + T
    speeds = [np.full_like(T, 2.0), np.full_like(T, 1.5), np.where(T < 5.0, 1.0, 2.0)]
    log = make_log(T, [lead, lead - 15.0, lead - 29.0], speeds)
    # max - min: 1.0 for the first 10 ticks, 0.5 for the last 10.
    assert m.mean_speed_difference(log) == pytest.approx(0.75)
    assert m.min_gaps(log) == {1: pytest.approx(15.0), 2: pytest.approx(14.0)}


def test_gaps_come_from_positions_not_the_logged_estimate():
    lead = 100.0 + T
    log = make_log(T, [lead, lead - 15.0], [np.ones_like(T)] * 2)
    log["gap_m"][log["vehicle_id"] == 1] = 14.0  # a vehicle's stale estimate
    assert m.min_gaps(log)[1] == pytest.approx(15.0)
    # Without the predecessor in the log, the logged gap is all there is.
    alone = {k: v[log["vehicle_id"] == 1] for k, v in log.items()}
    assert m.min_gaps(alone)[1] == pytest.approx(14.0)


def test_gaps_from_positions_when_the_log_has_none():
    lead = 100.0 + T
    log = make_log(T, [lead, lead - 12.0], [np.ones_like(T)] * 2, gap_logged=False)
    assert m.min_gaps(log)[1] == pytest.approx(12.0)
    assert m.compute_metrics(log)["p95_platooning_error_m"] == pytest.approx(3.0)


def test_unaligned_vehicle_logs_interpolate():
    # Vehicle 1 ticks halfway between the leader's ticks (two clocks, one merged log).
    lead = make_log(T, [10.0 * T], [np.full_like(T, 10.0)])
    t1 = T[:-1] + 0.25
    f = make_log(t1, [10.0 * t1, 10.0 * t1 - 15.0], [np.full_like(t1, 10.0)] * 2, gap_logged=False)
    keep = f["vehicle_id"] == 1
    log = {k: np.concatenate([lead[k], f[k][keep]]) for k in lead}
    assert m.min_gaps(log)[1] == pytest.approx(15.0)
    _, diff = m.speed_difference_series(log)
    assert np.nanmax(diff) == pytest.approx(0.0)


def test_collisions_count_pairs_below_half_lengths():
    lead = 100.0 + T
    f1 = lead - np.where(T < 5.0, 15.0, 0.7)  # 0.7 m < (0.779 + 0.97) / 2 -> collided
    f2 = f1 - 15.0
    log = make_log(T, [lead, f1, f2], [np.ones_like(T)] * 3)
    lengths = {0: 0.779, 1: 0.97, 2: 0.779}
    count, per = m.collisions(log, lengths)
    assert count == 1 and per == {1: True, 2: False}
    # Without lengths only an overlap of centres counts.
    assert m.collisions(log, {})[0] == 0


def test_string_stability_ratio_of_peak_errors():
    lead = 100.0 + T
    f1 = lead - 15.0 - np.where(T == 3.0, 2.0, 0.0)
    f2 = f1 - 15.0 - np.where(T == 4.0, 1.0, 0.0)
    log = make_log(T, [lead, f1, f2], [np.ones_like(T)] * 3)
    # f1's error peaks at 2 m (T = 3 s); f2 moves with f1 then, and its own error peaks
    # at 1 m (T = 4 s): errors halve along the string.
    ratio, per = m.string_stability(log)
    assert per == {2: pytest.approx(0.5)}
    assert ratio == pytest.approx(0.5)
    f2_amplified = lead - 30.0 - np.where(T == 4.0, 3.0, 0.0)
    log = make_log(T, [lead, f1, f2_amplified], [np.ones_like(T)] * 3)
    assert m.string_stability(log)[0] == pytest.approx(1.5)
    one = make_log(T, [lead, lead - 15.0], [np.ones_like(T)] * 2)
    assert math.isnan(m.string_stability(one)[0])


def test_delivery_ratio_from_cumulative_counters():
    lead = 100.0 + T
    ticks = np.arange(len(T))
    received = [np.zeros_like(ticks), 3 * ticks, 2 * ticks]
    lost = [np.zeros_like(ticks), ticks, 2 * ticks]
    log = make_log(
        T, [lead, lead - 15, lead - 30], [np.ones_like(T)] * 3, received=received, lost=lost
    )
    # Finals: received 57 + 38, lost 19 + 38.
    assert m.delivery_ratio(log) == pytest.approx(95 / 152)


def test_compute_metrics_keys_and_json_safety():
    lead = 100.0 + T
    log = make_log(T, [lead, lead - 15.0], [np.ones_like(T)] * 2)
    out = m.compute_metrics(log, {0: 1.0, 1: 1.0})
    for key in m.METRIC_KEYS:
        assert key in out
    assert out["collisions"] == 0
    safe = m.json_safe(out)
    assert safe["string_stability"] is None and safe["delivery_ratio"] is None
    assert set(safe["per_follower"]) == {"1"}
