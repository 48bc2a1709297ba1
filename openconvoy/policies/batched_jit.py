"""``BatchedClassical.act_batch`` compiled: ``ClassicalPolicy.act`` as one numba loop over rows.

``policies.batched``'s numpy code makes ~100 array calls per batch; this kernel walks
the rows once instead (~40 µs against ~260 µs for 1,024 x 2 rows). Each row is
``ClassicalPolicy.act`` written again: the same IEEE doubles in the same order
(observations widened from float32 as ``tolist`` does, Python's ``min``/``max`` as
written, libm's ``atan2`` and ``hypotf`` through ``math``; no fastmath), so actions agree
with ``act`` bit for bit
(``tests/policies/test_batched_jit.py``), each row keeping its own PID integrator.

The configuration and the layout's offsets go in as two arrays packed once per policy
(``pack``), not as globals, so one compiled kernel serves every preset. Compiled with
``envs.vector.jit``'s options (no reference counting, cached on disk by numba) but not
through it: policies import ``core`` only (DESIGN.md's import rule). This kernel calls no
kernel of another module, so numba's own check of this file keeps its cache right.
Importing this module without numba raises ``DependencyMissing`` and ``BatchedClassical``
runs its numpy code.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from openconvoy.core.errors import DependencyMissing
from openconvoy.core.observation import LOOKAHEAD_S
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.policies.classical import ClassicalConfig

try:
    import numba as _numba
except ImportError as exc:  # pragma: no cover - the extra is installed by `make test`
    raise DependencyMissing(
        "a compiled act_batch needs numba: pip install 'openconvoy[batched]'"
    ) from exc

_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy", "_nrt": False}


def bare_kernel(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled without reference counting (it allocates no array), no fastmath."""
    return _numba.njit(**_OPTIONS)(fn)


def bare_inline(fn: Callable[..., Any]) -> Any:
    """A ``bare_kernel`` that LLVM inlines into its callers."""
    return _numba.njit(**_OPTIONS, forceinline=True)(fn)


# Where each entry sits in the packed arrays (the layout of ``pack``'s output).
_I_OWN, _I_PATH, _I_FOLLOWER, _I_LOOKAHEAD, _I_PID, _I_STANLEY, _I_NT, _I_TARGETS = range(8)
_F_STALE, _F_KP, _F_KI, _F_KD, _F_DT, _F_LIM, _F_REAR, _F_VMAX, _F_GAIN, _F_SOFT, _F_HMAX = range(
    11
)


def pack(config: ClassicalConfig) -> tuple[np.ndarray, np.ndarray]:
    """``config`` as the kernel's ``(ints, floats)``: offsets into a row and kinds (int64),
    gains and limits (float64, SI). Targets nearest first (``pred_1`` .. ``pred_M``, then
    ``leader``), each as (offset of its newest state, offset of its derived features)."""
    lay = config.member.layout
    names = (*lay.targets[1:], "leader")
    j = int(np.argmin([abs(t - config.heading.lookahead_s) for t in LOOKAHEAD_S]))
    ints = [
        lay.own_offset,
        lay.path_offset,
        lay.slot_offset("follower"),
        j,
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


@bare_inline
def _leader_in_preds(obs, r, ints):  # pragma: no cover
    """The leader's newest state equals a predecessor slot's (``_leader_in_preds``)."""
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


@bare_inline
def _scan(obs, r, ints, stale_after):  # pragma: no cover
    """One pass over the targets nearest first (``ClassicalPolicy._targets``): lost, any
    valid, any fresh, v_ref, the sum and count of fresh errors, the nearest fresh target's
    speed, error and desired gap."""
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


@bare_inline
def _stale_caps(obs, r, ints, cfg, speed, v_ref, own):  # pragma: no cover
    """``speed`` lowered by each stale target's two limits, nearest first (Python's ``min``)."""
    kp, kd = cfg[_F_KP], cfg[_F_KD]
    for i in range(ints[_I_NT]):
        s, d = ints[_I_TARGETS + 2 * i], ints[_I_TARGETS + 2 * i + 1]
        if obs[r, d + 4] > 0.5 and obs[r, s + 5] > cfg[_F_STALE]:
            e, ts = np.float64(obs[r, d + 2]), np.float64(obs[r, d + 3])
            a = v_ref + kp * e + kd * (v_ref - own)
            b = ts + kp * e + kd * (ts - own)
            if a < speed:
                speed = a
            if b < speed:
                speed = b
    return speed


@bare_inline
def _heading(obs, r, ints, cfg, own):  # pragma: no cover
    """``_heading_change`` then ``make_action``'s clip (rad)."""
    p = ints[_I_PATH]
    change = 0.0
    if not obs[r, p + 8] < 0.5:
        if ints[_I_STANLEY]:
            cross, err = np.float64(obs[r, p]), np.float64(obs[r, p + 1])
            change = err + math.atan2(cfg[_F_GAIN] * cross, cfg[_F_SOFT] + abs(own))
        else:
            j = ints[_I_LOOKAHEAD]
            x, y = np.float64(obs[r, p + 2 + 2 * j]), np.float64(obs[r, p + 3 + 2 * j])
            if not (x == 0.0 and y == 0.0):
                change = math.atan2(y, x)
    hmax = cfg[_F_HMAX]
    if -hmax > change:
        change = -hmax
    if hmax < change:
        change = hmax
    return change


@bare_inline
def _speed(obs, r, ints, cfg, integral, own):  # pragma: no cover
    """One row's speed setpoint (m/s), ``act``'s speed law; writes the row's integrator.
    Returns -1.0 where the row stops (a target lost, or none valid)."""
    lost, any_valid, fresh, v_ref, total, n, near_v, near_e, near_d = _scan(
        obs, r, ints, cfg[_F_STALE]
    )
    if lost or not any_valid:
        integral[r] = 0.0
        return -1.0
    kp, kd = cfg[_F_KP], cfg[_F_KD]
    speed = math.inf
    if fresh:
        error = total / n
        if cfg[_F_REAR] > 0.0:
            f = ints[_I_FOLLOWER]
            rear = 0.0
            if not obs[r, f + 6] < 0.5:  # hypotf on the float32 dx, dy, as ``act``
                rear = np.float64(math.hypot(obs[r, f], obs[r, f + 1])) - near_d
            error -= cfg[_F_REAR] * rear
        if ints[_I_PID]:
            lim = cfg[_F_LIM]
            acc = integral[r] + error * cfg[_F_DT]
            if -lim > acc:
                acc = -lim
            if lim < acc:
                acc = lim
            integral[r] = acc
        speed = v_ref + kp * error + cfg[_F_KI] * integral[r] + kd * (v_ref - own)
        cap = near_v + kp * near_e + kd * (near_v - own)
        if cap < speed:
            speed = cap
    else:
        integral[r] = 0.0
    speed = _stale_caps(obs, r, ints, cfg, speed, v_ref, own)
    if 0.0 > speed:
        speed = 0.0
    if cfg[_F_VMAX] < speed:
        speed = cfg[_F_VMAX]
    return speed


@bare_kernel
def act_rows(obs, integral, ints, cfg, out):  # pragma: no cover
    """``ClassicalPolicy.act`` for each row of ``obs`` ``(n, D)`` float32 into ``out``
    ``(n, 2)`` float32 (speed m/s, heading change rad); ``integral`` ``(n,)`` float64 is
    each row's PID integrator, read and written; ``ints``, ``cfg`` from ``pack``."""
    for r in range(obs.shape[0]):
        own = np.float64(obs[r, ints[_I_OWN]])
        speed = _speed(obs, r, ints, cfg, integral, own)
        if speed == -1.0:
            out[r, 0] = 0.0
            out[r, 1] = 0.0
        else:
            out[r, 0] = speed
            out[r, 1] = _heading(obs, r, ints, cfg, own)
