"""The twins that remain, each against its reference on random inputs (issue 21), and the
rules the kernels compile from their home modules, compiled against themselves in Python.

A twin is batched code written a second time for speed (``benchmarks/twins.py`` counts
them); these properties hold each alone, where the lockstep tests of ``test_vector_env``
hold them only through whole episodes.
"""

from __future__ import annotations

import math

import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

import numba
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms.loss import counter_uniform
from openconvoy.core import estimate, ladder, safety, spacing
from openconvoy.envs import gps, plant
from openconvoy.envs.vector import math as vmath
from openconvoy.envs.vector.channel import counter_uniform4
from openconvoy.envs.vector.gps import counter_normals
from openconvoy.envs.vector.member import speed_gap  # registers the rules with numba
from openconvoy.envs.vector.plant import ROWS  # noqa: F401 - registers the plant's rules

FAST = settings(max_examples=200, deadline=None)
u64 = st.integers(0, 2**64 - 1)
u32 = st.integers(0, 2**32 - 1)
speed = st.floats(-5.0, 60.0)
positive = st.floats(0.01, 20.0)
gap = st.floats(-5.0, 200.0)


@FAST
@given(u64, u32, u32, u32, u32)
def test_counter_uniform4_is_counter_uniform(key: int, w0: int, w1: int, w2: int, w3: int) -> None:
    compiled = counter_uniform4(np.uint64(key), w0, w1, w2, w3)
    assert compiled == counter_uniform(key, w0, w1, w2, w3)


@FAST
@given(u64, st.integers(0, 64), st.integers(0, 10**6))
def test_counter_normals_are_gps_noise_draws(key: int, vehicle: int, tick: int) -> None:
    u1 = counter_uniform(key, vehicle, tick, 0)
    u2 = counter_uniform(key, vehicle, tick, 1)
    assert counter_normals(np.uint64(key), vehicle, tick) == gps.box_muller(u1, u2)


@FAST
@given(st.floats(-1e6, 1e6))
def test_wrap_is_the_scalar_modulo(a: float) -> None:
    # ConvoyEnv's plant: (h + pi) % 2pi - pi on Python floats; the kernels' fast paths
    # must round the same
    assert vmath.wrap(a) == (a + math.pi) % (2.0 * math.pi) - math.pi


# vehicle distances (m): none so small its square underflows (norm's stated range)
metres = st.just(0.0) | st.floats(1e-9, 1e4) | st.floats(-1e4, -1e-9)


@FAST
@given(metres, metres)
def test_norm_is_hypot_within_an_ulp(dx: float, dy: float) -> None:
    ref = math.hypot(dx, dy)
    assert abs(vmath.norm(dx, dy) - ref) <= math.ulp(ref)


def _compiled(fn):
    """``fn`` compiled by numba, as the kernels compile it (the rules it calls registered
    by the batched modules' import)."""
    return numba.njit(error_model="numpy")(fn)


_SPEED_GAP = _compiled(spacing.speed_gap_m)
_REDUCTION = _compiled(safety.gap_reduction_m)
_TOO_CLOSE = _compiled(safety.too_close)
_TRAVEL = _compiled(estimate.reckoned_travel)
_ACC = _compiled(ladder.acc_speed_mps)
_LAG = _compiled(plant.lag_speed_change)
_SLEW = _compiled(plant.slewed_yaw_rate)
_PI = _compiled(plant.pi_speed_loop)
_FRICTION = _compiled(plant.friction_speed)


@FAST
@given(st.sampled_from([1, 2]), speed, st.floats(0, 10), st.floats(0, 3), st.floats(0, 0.1))
def test_spacing_gap_compiled_is_the_rule(
    kind: int, v: float, s: float, h: float, q: float
) -> None:
    assert _SPEED_GAP(kind, v, s, h, q) == spacing.speed_gap_m(kind, v, s, h, q)
    assert speed_gap(np.array([kind, 15.0, s, h, q]), v) == spacing.speed_gap_m(kind, v, s, h, q)


@FAST
@given(
    speed,
    speed,
    st.floats(0, 1),
    st.floats(0, 1),
    positive,
    positive | st.just(math.inf),
    st.floats(-3, 3),
)
def test_braking_rule_compiled_is_the_rule(
    ego: float, pred: float, reaction: float, lag: float, decel: float, pdecel: float, acc: float
) -> None:
    args = (ego, pred, reaction, lag, decel, pdecel, acc)
    assert _REDUCTION(*args) == safety.gap_reduction_m(*args)


@FAST
@given(
    gap | st.just(math.inf),
    speed | st.just(math.nan),
    speed | st.just(math.nan),
    positive,
    st.floats(-3, 3),
)
def test_too_close_compiled_is_the_rule(
    bumper: float, closing: float, ego: float, pred_decel: float, accel: float
) -> None:
    rule = (4.0, 0.15, 0.5, 0.3)
    expected = safety.too_close(bumper, closing, ego, pred_decel, accel, rule)
    assert _TOO_CLOSE(bumper, closing, ego, pred_decel, accel, np.array(rule)) == expected
    gap_rule = safety.BrakingGap(*rule)
    assert (
        gap_rule.too_close(bumper, closing, None if math.isnan(ego) else ego, pred_decel, accel)
        == expected
    )


@FAST
@given(speed, st.floats(0, 5), st.floats(0, 1), positive | st.just(math.inf))
def test_dead_reckoning_compiled_is_the_rule(
    v: float, age: float, fresh: float, decel: float
) -> None:
    assert _TRAVEL(v, age, fresh, decel) == estimate.reckoned_travel(v, age, fresh, decel)


@FAST
@given(gap, st.floats(-10, 10), speed, gap, st.floats(0, 3), positive)
def test_acc_fallback_compiled_is_the_rule(
    rng: float, rate: float, ego: float, desired: float, extra: float, gain: float
) -> None:
    args = (rng, rate, ego, desired, extra, gain)
    assert _ACC(*args) == ladder.acc_speed_mps(*args)


@FAST
@given(speed, speed, positive, positive, positive, st.floats(0, 0.5))
def test_lag_speed_loop_compiled_is_the_rule(
    v_cmd: float, v: float, tau: float, acc: float, dec: float, brk: float
) -> None:
    args = (v_cmd, v, tau, acc, dec, brk, 0.05)
    assert _LAG(*args) == plant.lag_speed_change(*args)


@FAST
@given(
    st.floats(-3.2, 3.2), speed, st.floats(-2, 2), positive, positive, positive, positive, positive
)
def test_heading_loop_compiled_is_the_rule(
    err: float, v: float, rd: float, tau: float, rmax: float, kappa: float, yaw: float, alat: float
) -> None:
    args = (err, v, rd, tau, rmax, kappa, yaw, alat, 0.05)
    assert _SLEW(*args) == plant.slewed_yaw_rate(*args)


@FAST
@given(
    speed,
    speed,
    speed,
    st.floats(-2, 2),
    st.integers(0, 3),
    st.integers(0, 3),
    st.sampled_from([0.0, 0.47]),
)
def test_pi_speed_loop_compiled_is_the_rule(
    v_cmd: float, v: float, ramp: float, integ: float, n1: int, n2: int, kin: float
) -> None:
    gains = (0.2, 0.3, 1.0, 0.25, 0.1, 0.004, kin)  # kp, ki, ff, tau_d, stop, drag, kin
    args = (v_cmd, v, ramp, integ, gains, 2.0, 4.0, 0.1, 0.5 * v_cmd, (n1, 0.02, n2, 0.02))
    assert _PI(*args) == plant.pi_speed_loop(*args)


@FAST
@given(
    speed | st.just(0.0),
    st.floats(-3, 3),
    st.floats(0, 0.5),
    positive,
    st.floats(0, 1),
    st.floats(0, 1),
    st.booleans(),
)
def test_friction_compiled_is_the_rule(
    v: float, drive: float, drag: float, tau: float, brk: float, kin: float, stopped: bool
) -> None:
    args = (v, drive, drag, tau, brk, kin, stopped, 0.02)
    assert _FRICTION(*args) == plant.friction_speed(*args)
