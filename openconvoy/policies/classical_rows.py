"""``ClassicalPolicy.act`` on the rows of a batch: one loop over rows, written once.

``act_rows`` walks each row of a ``(n, D)`` float32 observation array as
``ClassicalPolicy.act`` walks one observation, with each row's PID integrator in an
array. The controllers' laws are ``core.controllers``'s own functions (``speed_law``,
``pd_speed``, ``integrated``, ``clamp``, ``stanley``, ``pure_pursuit``), called here as the
scalar policy calls them; what this module adds is the walk over the layout's targets
without lists (``_scan``, ``_stale_caps``), the twin of ``ClassicalPolicy._targets``
(property-tested against ``act`` on random observations,
``tests/policies/test_batched_jit.py``).

Plain Python on floats and arrays: ``policies.batched_jit`` compiles these same
functions with numba (~40 µs for 1,024 x 2 rows); without numba ``BatchedClassical``
runs them as they are (slow, and the same bits). Observations are widened from float32
as ``tolist`` does, Python's ``min``/``max`` as written, the follower's distance as
numpy's float32 ``hypot``; no fastmath, so actions agree with ``act`` bit for bit.

The configuration and the layout's offsets go in as two arrays packed once per policy
(``pack``), not as globals, so one compiled kernel serves every preset.
"""

from __future__ import annotations

import math

import numpy as np

from openconvoy.core.controllers import (
    clamp,
    integrated,
    pd_speed,
    pure_pursuit,
    speed_law,
    stanley,
)
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.policies.classical import ClassicalConfig, lookahead_index

# Where each entry sits in the packed arrays (the layout of ``pack``'s output).
_I_OWN, _I_PATH, _I_FOLLOWER, _I_LOOKAHEAD, _I_PID, _I_STANLEY, _I_NT, _I_TARGETS = range(8)
_F_STALE, _F_KP, _F_KI, _F_KD, _F_DT, _F_LIM, _F_REAR, _F_VMAX, _F_GAIN, _F_SOFT, _F_HMAX = range(
    11
)
STOP = -1.0
"""``_speed``'s answer for a row that stops (a target lost, or none valid)."""


def pack(config: ClassicalConfig) -> tuple[np.ndarray, np.ndarray]:
    """``config`` as ``act_rows``'s ``(ints, floats)``: offsets into a row and kinds
    (int64), gains and limits (float64, SI). Targets nearest first (``pred_1`` ..
    ``pred_M``, then ``leader``), each as (offset of its newest state, offset of its
    derived features). What ``ClassicalPolicy.act`` reads of ``config``
    (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    lay = config.member.layout
    names = (*lay.targets[1:], "leader")
    ints = [
        lay.own_offset,
        lay.path_offset,
        lay.slot_offset("follower"),
        lookahead_index(config.heading),
        int(config.speed.kind == "pid"),
        int(config.heading.kind == "stanley"),
        len(names),
    ]
    for name in names:
        ints += [lay.slot_offset(name), lay.target_offset(name)]
    c, h = config.speed, config.heading
    floats = [
        # An age compares with the limit as ``act`` compares a float32 observation's
        # element with it: the limit rounded to float32 (``ClassicalPolicy._stale_after``).
        float(np.float32(config.member.fresh_age_s)),
        c.kp,
        c.ki,
        c.kd,
        1.0 / config.control_rate_hz,
        c.integral_limit,
        config.rear_weight,
        config.speed_limit_mps,
        h.gain,
        h.softening_mps,
        MAX_HEADING_CHANGE_RAD,
    ]
    return np.array(ints, dtype=np.int64), np.array(floats, dtype=np.float64)


def _leader_in_preds(obs, r, ints):
    """The leader's newest state equals a predecessor slot's: twin of
    ``ClassicalPolicy._leader_in_preds`` (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    nt = ints[_I_NT]
    leader = ints[_I_TARGETS + 2 * (nt - 1)]
    for i in range(nt - 1):
        p = ints[_I_TARGETS + 2 * i]
        same = True
        for f in range(7):
            if not obs[r, leader + f] == obs[r, p + f]:
                same = False
                break
        if same:
            return True
    return False


def _scan(obs, r, ints, stale_after):
    """One pass over the targets nearest first (twin of ``ClassicalPolicy._targets``):
    lost, any valid, any fresh, v_ref, the sum and count of fresh errors, the nearest
    fresh target's speed, error and desired gap (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    nt = ints[_I_NT]
    lost, any_valid, have_fresh = False, False, False
    v_ref, fresh_sum, fresh_n = 0.0, 0.0, 0
    near_speed, near_err, near_desired = 0.0, 0.0, 0.0
    for i in range(nt):
        s, d = ints[_I_TARGETS + 2 * i], ints[_I_TARGETS + 2 * i + 1]
        if obs[r, d + 4] > 0.5:
            speed = np.float64(obs[r, d + 3])
            if not any_valid:
                v_ref = speed
                any_valid = True
            if not obs[r, s + 5] > stale_after:
                err = np.float64(obs[r, d + 2])
                fresh_sum += err
                fresh_n += 1
                if not have_fresh:
                    near_speed, near_err = speed, err
                    near_desired = np.float64(obs[r, d + 1])
                    have_fresh = True
        elif obs[r, s + 6] > 0.5 and (i != nt - 1 or not _leader_in_preds(obs, r, ints)):
            lost = True
    return (
        lost,
        any_valid,
        have_fresh,
        v_ref,
        fresh_sum,
        fresh_n,
        near_speed,
        near_err,
        near_desired,
    )


def _stale_caps(obs, r, ints, cfg, speed, v_ref, own):
    """``speed`` lowered by each stale target's two caps, nearest first: the stale loop
    of ``ClassicalPolicy.act`` (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    kp, kd = cfg[_F_KP], cfg[_F_KD]
    for i in range(ints[_I_NT]):
        s, d = ints[_I_TARGETS + 2 * i], ints[_I_TARGETS + 2 * i + 1]
        if obs[r, d + 4] > 0.5 and obs[r, s + 5] > cfg[_F_STALE]:
            e, ts = np.float64(obs[r, d + 2]), np.float64(obs[r, d + 3])
            speed = min(
                speed, pd_speed(e, v_ref, v_ref - own, kp, kd), pd_speed(e, ts, ts - own, kp, kd)
            )
    return speed


def _heading(obs, r, ints, cfg, own):
    """``ClassicalPolicy._heading_change`` then ``make_action``'s clip (rad)
    (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    p = ints[_I_PATH]
    change = 0.0
    if not obs[r, p + 8] < 0.5:
        if ints[_I_STANLEY]:
            err, cross = np.float64(obs[r, p + 1]), np.float64(obs[r, p])
            change = stanley(err, cross, own, cfg[_F_GAIN], cfg[_F_SOFT])
        else:
            j = ints[_I_LOOKAHEAD]
            x, y = np.float64(obs[r, p + 2 + 2 * j]), np.float64(obs[r, p + 3 + 2 * j])
            change = pure_pursuit(x, y)
    return clamp(change, -cfg[_F_HMAX], cfg[_F_HMAX])


def _speed(obs, r, ints, cfg, integral, own):
    """One row's speed setpoint (m/s), ``act``'s speed law; writes the row's integrator.
    Returns ``STOP`` where the row stops (a target lost, or none valid): the speed half
    of ``ClassicalPolicy.act`` (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    lost, any_valid, fresh, v_ref, total, n, near_v, near_e, near_d = _scan(
        obs, r, ints, cfg[_F_STALE]
    )
    if lost or not any_valid:
        integral[r] = 0.0
        return STOP
    kp, kd = cfg[_F_KP], cfg[_F_KD]
    speed = math.inf
    if fresh:
        error = total / n
        if cfg[_F_REAR] > 0.0:
            f = ints[_I_FOLLOWER]
            rear = 0.0
            if not obs[r, f + 6] < 0.5:  # float32 hypot of the float32 dx, dy, as ``act``
                rear = np.float64(np.hypot(obs[r, f], obs[r, f + 1])) - near_d
            error -= cfg[_F_REAR] * rear
        if ints[_I_PID]:
            integral[r] = integrated(integral[r], error, cfg[_F_DT], cfg[_F_LIM])
        speed = speed_law(error, v_ref, v_ref - own, integral[r], kp, cfg[_F_KI], kd)
        speed = min(speed, pd_speed(near_e, near_v, near_v - own, kp, kd))
    else:
        integral[r] = 0.0
    speed = _stale_caps(obs, r, ints, cfg, speed, v_ref, own)
    return clamp(speed, 0.0, cfg[_F_VMAX])


def act_rows(obs, integral, ints, cfg, out):
    """``ClassicalPolicy.act`` for each row of ``obs`` ``(n, D)`` float32 into ``out``
    ``(n, 2)`` float32 (speed m/s, heading change rad); ``integral`` ``(n,)`` float64 is
    each row's PID integrator, read and written; ``ints``, ``cfg`` from ``pack``
    (tests/policies/test_batched_jit.py::test_the_rows_are_act_on_random_observations)."""
    for r in range(obs.shape[0]):
        own = np.float64(obs[r, ints[_I_OWN]])
        speed = _speed(obs, r, ints, cfg, integral, own)
        if speed == STOP:
            out[r, 0] = 0.0
            out[r, 1] = 0.0
        else:
            out[r, 0] = speed
            out[r, 1] = _heading(obs, r, ints, cfg, own)


ROW_FUNCTIONS = ("_leader_in_preds", "_scan", "_stale_caps", "_heading", "_speed")
"""The helpers ``act_rows`` calls, which ``batched_jit`` compiles inline."""
