"""The mpc controller family's QP (core.mpc): prediction, constraints, and DAQP against a
reference solve (OSQP's direct API at tight tolerances) on random problems."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from openconvoy.core.errors import ConfigError
from openconvoy.core.mpc import (
    MPCConfig,
    PlantModel,
    Prediction,
    Target,
    build_qp,
    discretize,
    solve,
)

LAG = PlantModel(speed_lag_s=0.3, accel_max_mps2=1.0, decel_max_mps2=1.0, max_speed_mps=5.0)
PI = PlantModel(
    speed_loop="pi", speed_kp=0.8, speed_ki=0.4, speed_ff=0.9, drive_lag_s=0.4, max_speed_mps=5.0
)


def test_discretize_matches_the_lag_solution() -> None:
    a, b = LAG.continuous()
    ad, bd = discretize(a, b, 0.1)
    # speed after 0.1 s of setpoint 2 from rest: 2 (1 - e^{-0.1/0.3})
    x = ad @ np.array([0.0, 0.0]) + bd * 2.0
    assert x[1] == pytest.approx(2.0 * (1.0 - math.exp(-0.1 / 0.3)), rel=1e-9)
    # position: the integral of that speed
    expect = 2.0 * (0.1 - 0.3 * (1.0 - math.exp(-0.1 / 0.3)))
    assert x[0] == pytest.approx(expect, rel=1e-9)


@pytest.mark.parametrize("model", [LAG, PI])
def test_condensed_prediction_equals_stepping_the_model(model: PlantModel) -> None:
    pred = Prediction(model, 15, 0.1)
    rng = np.random.default_rng(1)
    u = rng.uniform(0.0, 4.0, 15)
    x0 = model.steady_state(1.3)
    x = x0.copy()
    for k in range(15):
        x = pred.ad @ x + pred.bd * u[k]
        assert (pred.Pv @ x0 + pred.Gv @ u)[k] == pytest.approx(x[1], abs=1e-12)
        assert (pred.Pp @ x0 + pred.Gp @ u)[k] == pytest.approx(x[0], abs=1e-12)


def _problem(
    h: int, v_now: float, gap_err: float, v_pred: float, model: PlantModel, cfg: MPCConfig
):
    pred = Prediction(model, h, cfg.step_s)
    times = cfg.step_s * np.arange(1, h + 1)
    position = 15.0 + gap_err + v_pred * times
    target = Target(position, 15.0, 0.0)
    speeds = np.full(h, v_pred)
    x0 = model.steady_state(v_now)
    closing = np.full(h, v_now - v_pred)
    return build_qp(cfg, pred, x0, v_now, v_now, [target], speeds, 0.8, closing, 0.4)


def _objective(qp, z: np.ndarray) -> float:
    return float(0.5 * z @ qp.H @ z + qp.f @ z)


@settings(max_examples=40, deadline=None)
@given(
    h=st.integers(3, 40),
    v_now=st.floats(0.0, 4.5),
    gap_err=st.floats(-8.0, 8.0),
    v_pred=st.floats(0.0, 4.5),
    pi=st.booleans(),
    w_du=st.floats(0.01, 10.0),
)
def test_daqp_matches_the_osqp_reference(h, v_now, gap_err, v_pred, pi, w_du) -> None:
    # A slack weight nearer the others keeps the ADMM reference well conditioned.
    cfg = MPCConfig(horizon=h, w_du=w_du, w_slack=100.0)
    qp = _problem(h, v_now, gap_err, v_pred, PI if pi else LAG, cfg)
    ours = solve(qp, "daqp")
    assert ours.ok
    ref = solve(qp, "osqp")
    # ADMM (the reference) can stop at its iteration cap on an ill-conditioned instance
    # (hypothesis found h=18, v_now=0, v_pred=2, w_du=0.25); DAQP is judged where the
    # reference has an answer.
    assume(ref.ok)
    # Feasible for the constraints it was given (to solver tolerance) ...
    n = qp.H.shape[0]
    az = qp.A @ ours.z
    assert np.all(ours.z >= qp.blower[:n] - 1e-6) and np.all(ours.z <= qp.bupper[:n] + 1e-6)
    assert np.all(az <= qp.bupper[n:] + 1e-5) and np.all(az >= qp.blower[n:] - 1e-5)
    # ... and as good as the reference optimum.
    f_ours, f_ref = _objective(qp, ours.z), _objective(qp, ref.z)
    assert f_ours <= f_ref + 1e-4 * max(1.0, abs(f_ref))
    assert np.max(np.abs(ours.z[:h] - ref.z[:h])) < 2e-2


def test_a_gap_too_short_slows_and_one_too_long_speeds_up() -> None:
    cfg = MPCConfig()
    close = solve(_problem(20, 2.0, -3.0, 2.0, LAG, cfg), "daqp")
    far = solve(_problem(20, 2.0, 3.0, 2.0, LAG, cfg), "daqp")
    assert close.z[0] < 2.0 < far.z[0]


def test_the_acceleration_limit_holds_in_the_prediction() -> None:
    cfg = MPCConfig(horizon=20)
    pred = Prediction(LAG, 20, cfg.step_s)
    qp = _problem(20, 0.5, 10.0, 3.0, LAG, cfg)
    sol = solve(qp, "daqp")
    v = pred.Pv @ LAG.steady_state(0.5) + pred.Gv @ sol.z[:20]
    acc = np.diff(np.concatenate([[0.5], v])) / cfg.step_s
    assert np.max(sol.z[20:]) == pytest.approx(0.0, abs=1e-6)  # no slack needed
    assert acc.max() <= LAG.accel_max_mps2 + 1e-6
    assert acc.max() > 0.9 * LAG.accel_max_mps2  # it wants to close 10 m: the limit binds


def test_the_braking_safe_gap_needs_the_slack_only_when_unavoidable() -> None:
    cfg = MPCConfig(horizon=20)
    # 1 m of bumper gap closing at 2 m/s on a car braking: cannot be kept, the slack opens
    qp = _problem(20, 3.0, -13.2, 1.0, LAG, cfg)
    sol = solve(qp, "daqp")
    assert sol.ok and np.max(sol.z[21:]) > 0.1
    # It brakes as hard as its model allows: the first step's deceleration at the limit.
    pred = Prediction(LAG, 20, cfg.step_s)
    v1 = (pred.Pv @ LAG.steady_state(3.0) + pred.Gv @ sol.z[:20])[0]
    assert (v1 - 3.0) / cfg.step_s == pytest.approx(-LAG.decel_max_mps2, abs=1e-3)


def test_hard_terminal_constraint_pins_the_end_of_the_horizon() -> None:
    cfg = MPCConfig(horizon=30, terminal="hard", safe_gap=False)
    pred = Prediction(LAG, 30, cfg.step_s)
    qp = _problem(30, 1.0, 1.0, 1.0, LAG, cfg)
    sol = solve(qp, "daqp")
    assert sol.ok
    x0 = LAG.steady_state(1.0)
    v = pred.Pv @ x0 + pred.Gv @ sol.z[:30]
    p = pred.Pp @ x0 + pred.Gp @ sol.z[:30]
    assert v[-1] == pytest.approx(1.0, abs=1e-6)
    assert 16.0 + 1.0 * 3.0 - p[-1] == pytest.approx(15.0, abs=1e-6)


def test_bad_names_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="solver"):
        MPCConfig(solver="cvxpy")
    with pytest.raises(ConfigError, match="plan_fallback"):
        MPCConfig(plan_fallback="guess")
    with pytest.raises(ConfigError, match="speed_loop"):
        PlantModel(speed_loop="pid")
