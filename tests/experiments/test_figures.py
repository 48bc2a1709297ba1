"""Figures that show what matters: a straight road's lateral deviation in centimetres,
and a policy drawn exactly over another named in the legend."""

from __future__ import annotations

import math

import numpy as np

from openconvoy.experiments import RunConfig, run_sim
from openconvoy.experiments.figures import road_frame, run_figures, same_as, straight_line


def test_a_straight_road_is_drawn_as_offset_from_the_leaders_line(tmp_path):
    run = run_sim(RunConfig(scenario="paper", policy="paper", duration_s=10.0, seed=0))
    vid = np.asarray(run.log["vehicle_id"])
    x, y = np.asarray(run.log["x_m"], float), np.asarray(run.log["y_m"], float)
    line = straight_line(x[vid == 0], y[vid == 0])
    assert line is not None
    along, off = road_frame(x[vid == 0], y[vid == 0], line)
    assert along[-1] - along[0] > 5.0  # metres of road
    assert np.max(np.abs(off)) < 1e-6  # the leader is its own line
    paths = run_figures(run.log, tmp_path, "(paper, paper)")
    assert all(p.stat().st_size > 10_000 for p in paths)
    # A curved road keeps its plan view.
    track = run_sim(RunConfig(scenario="track", policy="paper", duration_s=40.0, seed=0))
    tv = np.asarray(track.log["vehicle_id"])
    tx, ty = np.asarray(track.log["x_m"], float), np.asarray(track.log["y_m"], float)
    assert straight_line(tx[tv == 0], ty[tv == 0]) is None
    assert straight_line(np.zeros(5), np.zeros(5)) is None  # a convoy at rest


def test_a_line_hidden_under_another_is_named():
    def rows(label, values):
        return [
            {"policy": label, "per": per, "p95": {"mean": v, "std": 0.0}}
            for per, v in zip((0.0, 0.3), values)
        ]

    table = rows("paper", [0.2, 0.4]) + rows("paper+ladder", [0.2, 0.4])
    table += rows("cacc", [0.2, 0.5]) + rows("copy", [0.2, 0.4])
    assert same_as(table, ["paper", "paper+ladder", "cacc", "copy"], "p95") == {
        "paper+ladder": "paper",
        "copy": "paper",
    }
    table = rows("a", [math.nan, 0.1]) + rows("b", [math.nan, 0.1 + 1e-6])
    assert same_as(table, ["a", "b"], "p95") == {}
