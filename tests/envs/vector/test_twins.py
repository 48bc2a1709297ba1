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
from hypothesis import example, given, settings
from hypothesis import strategies as st

from openconvoy.comms import loss
from openconvoy.comms.loss import counter_uniform
from openconvoy.core import estimate, ladder, observation, safety, spacing, state
from openconvoy.core import ranging as core_ranging
from openconvoy.core.errors import ConfigError
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.member import ConvoyMember, Frame, MemberConfig
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.core.spacing import SpacingConfig
from openconvoy.core.state import VehicleState
from openconvoy.core.trail import Trail
from openconvoy.envs import gps, plant, scenarios
from openconvoy.envs import reward as reward_mod
from openconvoy.envs.channel import advance_kinematics
from openconvoy.envs.path import Path
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.ranging_noise import ranging_normals
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.vector import channel as vchannel
from openconvoy.envs.vector import gps as vgps
from openconvoy.envs.vector import leader as vleader
from openconvoy.envs.vector import math as vmath
from openconvoy.envs.vector import measures as vmeasures
from openconvoy.envs.vector import member as vmember
from openconvoy.envs.vector import observation as _kernels  # noqa: F401 - registers ego_state
from openconvoy.envs.vector import plant as vplant
from openconvoy.envs.vector import ranging as vranging
from openconvoy.envs.vector.channel import counter_uniform4
from openconvoy.envs.vector.gps import counter_normals
from openconvoy.envs.vector.member import speed_gap  # registers the rules with numba
from openconvoy.envs.vector.plant import COS_H, HEADING, ROWS, SIN_H, SPEED, X, Y
from openconvoy.envs.vector.rx import FIELDS, HC, HH, HS, HV, HX, HY, T
from openconvoy.envs.vector.trail import (
    CAPACITY,
    TAIL,
    finish,
    head_s,
    point_at,
    project,
    trail_add,
)
from openconvoy.envs.vehicles import VEHICLE_PRESETS

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
@given(u64)
def test_channel_mix_is_splitmix(z: int) -> None:
    assert vchannel._mix(np.uint64(z)) == _splitmix(z)


def _splitmix(z: int) -> int:
    """SplitMix64's finalizer as ``comms.loss`` writes it: one round of ``counter_state``
    from ``z - SPLITMIX_GOLDEN`` with the word 0."""
    return loss.counter_state((z - loss.SPLITMIX_GOLDEN) % 2**64, 0)


@FAST
@given(u64, u32, u32, u32)
def test_channel_draw_bits_are_the_loss_draws(key: int, s: int, r: int, number: int) -> None:
    # the 53 bits of counter_uniform(key, s, r, number, DRAW_LOSS), from the link's state
    bits = vchannel._draw_bits(np.uint64(loss.counter_state(key, s)), r, number)
    uniform = counter_uniform(key, s, r, number, vchannel.DRAW_LOSS)
    assert int(bits) * loss.UNIT_53 == uniform and int(bits) < 2**53


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
# positions on a centimetre grid: no distance so small its square underflows (as above)
centimetres = st.integers(-3000, 3000).map(lambda k: k / 100.0)


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


_WRAP = _compiled(state.wrap_angle)
_EGO = _compiled(observation.ego_state)
angle = st.floats(-1e6, 1e6)


@FAST
@given(angle)
def test_wrap_angle_compiled_is_the_modulo(a: float) -> None:
    # one rule for vehicles, ConvoyEnv and the kernels: its fast paths round as the modulo
    want = (a + math.pi) % (2.0 * math.pi) - math.pi
    assert state.wrap_angle(a) == want
    assert _WRAP(a) == want


@FAST
@given(angle, metres, metres, angle, st.floats(-20.0, 20.0))
def test_ego_state_compiled_is_the_rule(
    heading: float, dx: float, dy: float, dh: float, age: float
) -> None:
    c, s = math.cos(heading), math.sin(heading)
    got = _EGO(c, s, dx, dy, dh, age)
    assert got == observation.ego_state(c, s, dx, dy, dh, age)
    assert 0.0 <= got[3] <= observation.MAX_AGE_S and -math.pi <= got[2] < math.pi


# A sender's run: per tick a heading change (rad), speed (m/s) and position noise (m).
_moves = st.lists(
    st.tuples(st.floats(-0.3, 0.3), st.floats(0.0, 6.0), st.floats(-0.05, 0.05)),
    min_size=2,
    max_size=160,
)


def _laid(
    moves: list[tuple[float, float, float]],
) -> tuple[Trail, tuple, tuple[float, float, float]]:
    """The same sends to a ``Trail`` and to a ring (B = T = 1, a ring of the whole
    capacity): the scalar trail, the ring's arrays and the sender's last state (x, y,
    heading)."""
    ring = np.zeros((1, 1, CAPACITY, 3)), np.zeros((1, 1, TAIL)), np.zeros((1, 1), np.int64)
    ref = Trail(0.2, CAPACITY)
    x = y = h = t = 0.0
    for dh, v, noise in moves:
        h += dh
        x, y, t = x + 0.1 * v * math.cos(h), y + 0.1 * v * math.sin(h), t + 0.1
        ref.add(x + noise, y - noise, h, v, t)
        trail_add(*ring, 0, 0, x + noise, y - noise, 0.2, t, v, math.cos(h), math.sin(h))
    return ref, ring, (x, y, h)


@settings(max_examples=120, deadline=None)
@given(
    _moves, st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(0.0, 30.0), st.floats(-5.0, 40.0)
)
def test_the_ring_trail_projects_and_reads_as_trail(
    moves: list[tuple[float, float, float]], qx: float, qy: float, gap: float, back: float
) -> None:
    """``vector.trail`` (rings, a hinted bisection, a walk that skips the sqrt where it
    can) against ``core.trail.Trail`` alone: the same breadcrumbs; a point ``gap`` m
    behind the head (off by ``qx``, ``qy``) projects to the same arc, cross track and
    heading; the path point ``back`` m behind the head is the same (within a few ulps of
    the trail's size: the kernels' ``norm`` is ``hypot`` within an ulp)."""
    ref, (tr, tail, n), (hx, hy, hh) = _laid(moves)
    assert n[0, 0] == len(ref)
    if len(ref) < 2:
        return
    x, y = hx - gap * math.cos(hh) + qx, hy - gap * math.sin(hh) + qy
    want = ref.project((hx, hy), hh, x, y, gap)
    arc, s, k, cross_seg, dx, dy, seg = project(
        tr, tail, n, 0, 0, hx, hy, hh, x, y, gap, math.nan, 0
    )
    cross, heading = finish(cross_seg, dx, dy, seg, hh)
    tol = 1e-9 * (1.0 + ref.head_s((hx, hy)))
    assert abs(arc - want.arc_to_head) <= tol and abs(s - want.s) <= tol
    assert abs(cross - want.cross_track) <= 1e-9 and abs(heading - want.heading) <= 1e-9
    s_head = head_s(tail, 0, 0, hx, hy)
    assert abs(s_head - ref.head_s((hx, hy))) <= tol
    px, py = point_at(tr, tail, n, 0, 0, hx, hy, hh, s_head - back, k + 1, s_head)
    wx, wy = ref.point_at((hx, hy), hh, s_head - back)
    assert abs(px - wx) <= tol and abs(py - wy) <= tol


# The member's twins (envs.vector.member) against core's rules and ConvoyMember's.


def HYPOT_ULP(want: tuple) -> object:  # noqa: N802 - reads as a constant tolerance
    """``want`` within a few ulps: a gap through ``core.estimate.closing_m``'s
    ``math.hypot``, which numba compiles to libm's ``hypot`` and CPython (3.10+) rounds
    correctly; the two differ in the last bit for some inputs (found by these tests)."""
    return pytest.approx(want, rel=1e-14, abs=1e-14)


def _history(x: float, y: float, v: float, h: float, t_msg: float) -> np.ndarray:
    """One link's R^i buffer (B = L = 1, depth 1) holding one message, its heading's
    cosine and sine as ``vector.rx`` pushes them."""
    hist = np.zeros((1, 1, 1, FIELDS))
    hist[0, 0, 0, [T, HX, HY, HV, HH]] = t_msg, x, y, v, h
    hist[0, 0, 0, HC], hist[0, 0, 0, HS] = math.cos(h), math.sin(h)
    return hist


coord = st.floats(-1e3, 1e3)
heading = st.floats(-math.pi, math.pi)
ages = st.floats(0.0, 5.0)


@FAST
@given(coord, coord, speed, heading, ages, st.floats(0, 1), st.floats(0.5, 3), positive)
def test_member_estimate_is_dead_reckon(
    x: float, y: float, v: float, h: float, age: float, fresh: float, stop: float, decel: float
) -> None:
    now = 100.0
    msg = VehicleState(1, now - age, x, y, v, h)
    want = estimate.dead_reckon(msg, now, fresh, stop, decel)
    got = vmember.estimate(
        _history(x, y, v, h, now - age), np.ones((1, 1), np.int64), np.array([decel]),
        0, 0, now, stop, fresh,
    )  # fmt: skip
    assert got[0] == (want is not None)
    if want is not None:
        assert got[1:] == (want.x, want.y, want.speed, want.heading, want.age)
    # no link, or a link never heard: invalid
    none = np.zeros((1, 1), np.int64)
    assert not vmember.estimate(_history(x, y, v, h, 0.0), none, np.ones(1), 0, 0, now, stop, 0)[0]
    assert not vmember.estimate(_history(x, y, v, h, 0.0), none + 1, np.ones(1), 0, -1, 1, 9, 0)[0]


@FAST
@given(st.sampled_from([0, 1, 2]), speed, st.floats(0, 40), st.floats(0, 10), st.floats(0, 3),
       st.floats(0, 0.1), st.floats(0, 10), st.floats(0, 10))  # fmt: skip
def test_member_pair_gap_is_the_spacing_rule(
    kind: int, v: float, dist: float, s0: float, h: float, q: float, lb: float, la: float
) -> None:
    sp = np.array([kind, dist, s0, h, q], float)
    want = spacing.pair_gap_m(kind, v, dist, s0, h, q, 0.5 * (lb + la))
    assert vmember.pair_gap(sp, v, lb, la) == want


@FAST
@given(st.floats(-1e3, 1e3) | st.just(-math.inf), st.floats(0, 1e3))
def test_member_link_age_is_the_message_age(newest: float, t: float) -> None:
    # ConvoyMember's age of a link's newest message: never negative, inf when unheard
    want = math.inf if newest == -math.inf else max(0.0, t - newest)
    assert vmember.link_age(np.array([[newest]]), 0, 0, t) == want


def _own(x: float, y: float, v: float, h: float) -> np.ndarray:
    """``own`` (``plant.ROWS``, B = 1, N = 1) of one vehicle, its heading's cosine and sine
    as the plant writes them."""
    own = np.zeros((ROWS, 1, 1))
    own[[X, Y, SPEED, HEADING, COS_H, SIN_H], 0, 0] = x, y, v, h, math.cos(h), math.sin(h)
    return own


@FAST
@given(coord, coord, speed, heading, coord, coord, speed, heading)
def test_member_gap_and_closing_is_the_estimate_rule(
    ox: float, oy: float, ov: float, oh: float, ex: float, ey: float, ev: float, eh: float
) -> None:
    own = VehicleState(1, 0.0, ox, oy, ov, oh)
    est = estimate.TargetEstimate(ex, ey, ev, eh, 0.0, False)
    got = vmember._gap_and_closing(
        _own(ox, oy, ov, oh), 0, 0, ex, ey, ev, math.cos(eh), math.sin(eh)
    )
    # numba's compiled math.hypot is not CPython's correctly rounded one: an ulp apart
    assert got == HYPOT_ULP(estimate.gap_and_closing(own, est))


def _member(needed: list[int], newest: list[float], lad: LadderConfig, **arrays) -> tuple:
    """A ``vector.member.Member`` for one convoy of a leader and one follower, whose
    ``needed`` links last heard at ``newest`` (s; -inf: never), with ``lad``; the rest
    zero unless given."""
    z = np.zeros((1, 1, 1, FIELDS))
    fields = {
        "low": np.zeros((1, 2)), "high": np.zeros((1, 2)), "hist": z,
        "hist_n": np.zeros((1, 1), np.int64), "newest": np.array([newest]),
        "needed": np.array([[-1] * len(needed), needed], np.int64),
        "pred_link": np.zeros(1, np.int64), "lead_link": np.full(2, -1, np.int64),
        "link_decel": np.ones(1), "decel": np.ones(2), "lengths": np.full(2, 4.0),
        "spacing": vmember.pack_spacing(SpacingConfig()), "ladder": vmember.pack_ladder(lad),
        "fresh_age": 0.5, "max_dh": 0.1, "rule": np.zeros((4, 1)), "lead_rule": np.zeros(4),
        "emergency": False,
    }  # fmt: skip
    fields.update(arrays)
    return vmember.Member(**fields)


@FAST
@given(
    st.lists(st.floats(0.0, 10.0) | st.just(-math.inf), min_size=1, max_size=3),
    st.floats(0.01, 3.0),
    st.floats(0.01, 3.0),
    st.floats(0.0, 10.0),
)
def test_member_rung_is_the_ladders_rung_of_the_oldest_needed(
    heard: list[float], degrade: float, extra: float, now: float
) -> None:
    lad = LadderConfig(enabled=True, degrade_after_s=degrade, stop_after_s=degrade + extra)
    m = _member(list(range(len(heard))), heard, lad)
    nan = np.full((2, 1, 2), math.nan)  # no ranging reading, no predecessor estimate
    got = vmember._rung(_own(0, 0, 0, 0).repeat(2, axis=2), 0, 1, m, nan, nan, now)
    oldest = max(max(0.0, now - t) for t in heard)
    assert ladder.MODES[got] == ladder.rung(oldest, lad)


# The channel's pure helpers (envs.vector.channel) against comms.loss and envs.channel.
@FAST
@given(
    st.lists(st.floats(0.0, 0.5), min_size=1, max_size=8).map(sorted),
    st.floats(0.0, 1.0, exclude_max=True),
)
def test_channel_quantile_delay_is_the_loss_models(samples: list[float], u: float) -> None:
    table = np.zeros((2, 9))
    table[1, : len(samples)] = samples
    got = vchannel._quantile_delay(table, 1, len(samples), u)
    assert got == loss.quantile_delay(samples, u)


@FAST
@given(coord, coord, speed, heading, st.floats(-8, 4), st.floats(-1, 1), st.floats(0, 0.5))
def test_channel_advance_is_advance_kinematics(
    x: float, y: float, v: float, h: float, a: float, w: float, d: float
) -> None:
    st_ = np.zeros((6, 1, 2))
    st_[:, 0, 1] = x, y, v, h, a, w
    out = np.full((6, 1, 2), math.nan)
    vchannel._advance(st_, 0, 1, d, out)
    assert tuple(out[:4, 0, 1]) == advance_kinematics(x, y, v, h, a, w, d)
    assert tuple(out[4:, 0, 1]) == (a, w) and np.isnan(out[:, 0, 0]).all()


@FAST
@given(st.floats(0.0, 1.0), st.integers(0, 2**53 - 1))
def test_channel_loss_threshold_is_the_float_comparison(per: float, m: int) -> None:
    # a counter draw m * 2**-53 (comms.loss.counter_uniform) is lost when below per
    assert (np.uint64(m) < vchannel.loss_threshold(per)) == (m * loss.UNIT_53 < per)


@FAST
@given(u64, st.integers(0, 1000), st.floats(0.0, 1.0), st.booleans(), st.booleans())
def test_channel_bernoulli_loses_by_the_counter_draw(
    key: int, number: int, per: float, sends: bool, row: bool
) -> None:
    # pairs (sender, receiver): (0, 1), (1, 0), (1, 2); vehicle 1 broadcasts ``number``
    pair_s, pair_r = np.array([0, 1, 1]), np.array([1, 0, 2])
    send = np.array([[False, sends, False]])
    lost = np.ones((1, 3), bool)
    draws = vchannel.Loss(
        np.array([key], np.uint64), np.full((1, 3), number), np.array([per]), np.zeros(3)
    )
    pairs = vchannel.Pairs(pair_s, pair_r, np.full(3, -1))
    vchannel._bernoulli(draws, send, pairs, np.array([row]), lost)
    for p in range(3):
        s, r = pair_s[p], pair_r[p]
        draw = counter_uniform(key, s, r, number, vchannel.DRAW_LOSS)
        assert lost[0, p] == (row and per > 0.0 and send[0, s] and draw < per)


# The leader's twins (envs.vector.leader) against envs.path.Path and the profiles.
# distinct vertices on a centimetre grid (``Path`` merges vertices under 1e-9 m apart)
_polyline = st.lists(st.tuples(centimetres, centimetres), min_size=2, max_size=12, unique=True)


def _road(path: Path, s: float) -> vleader.LeaderRoad:
    """``path`` as ``LeaderDriver`` packs it, one leader at arc length ``s`` (m)."""
    seg = np.concatenate([path._a, path._seg_dir, path._seg_len[:, None]], axis=1)
    one = np.zeros(1)
    return vleader.LeaderRoad(
        seg, np.asarray(path._s, float), path.closed, path.length, np.array([s]),
        one, one, one, 0, np.zeros(4),
    )  # fmt: skip


@settings(max_examples=100, deadline=None)
@given(_polyline, st.booleans(), st.floats(0, 1), coord, coord, st.floats(-50, 5e3))
@example([(0.0, 0.0), (1.0, 0.0), (2.0, 0.0)], False, 0.5, 1.0, 0.5, 1.0)  # s at a vertex
def test_leader_project_and_segment_are_the_paths(
    points: list[tuple[float, float]], closed: bool, frac: float, qx: float, qy: float, s: float
) -> None:
    try:
        path = Path(np.array(points), closed)
    except ConfigError:  # fewer than two distinct points
        return
    road = _road(path, frac * path.length)
    hint = road.s[0]
    own = np.zeros((ROWS, 1, 1))
    own[X, 0, 0], own[Y, 0, 0] = qx, qy
    vleader._project(own, road)
    assert road.s[0] == path.project(qx, qy, hint, vleader.WINDOW_M)
    assert vleader._segment(road.seg_s, len(path._seg_len), s) == path._segment(s)


@FAST
@given(st.sampled_from([0, 1, 2]), st.floats(0, 200), st.floats(0, 1e3), speed)
def test_leader_profile_is_the_scenarios(kind: int, t: float, s: float, target: float) -> None:
    want = (target, scenarios.paper_speed(t, s), scenarios.emergency_speed(t, s))[kind]
    assert vleader._profile(kind, t, s, target) == want


@FAST
@given(u64, st.integers(0, 10**6), st.floats(0, 5), st.booleans())
def test_gps_sense_is_gps_noise(key: int, tick: int, sigma: float, row: bool) -> None:
    own = np.arange(ROWS * 3, dtype=float).reshape(ROWS, 1, 3)
    sensed = np.full((6, 1, 3), math.nan)
    vgps.sense(own, np.array([tick]), np.array([key], np.uint64), sigma, np.array([row]), sensed)
    if not row:
        assert np.isnan(sensed).all()
        return
    dx, dy = gps.gps_noise(gps.vehicle_states(key, 3), sigma, tick)
    assert list(sensed[0, 0]) == [x + e for x, e in zip(own[0, 0], dx, strict=True)]
    assert list(sensed[1, 0]) == [y + e for y, e in zip(own[1, 0], dy, strict=True)]
    assert (sensed[2:, 0] == own[2:6, 0]).all()


reading = st.tuples(st.floats(0.5, 80.0), st.floats(-10.0, 10.0))
# each rung about as often: coop, degraded, stop
rung_age = st.floats(0.0, 0.5) | st.floats(0.5, 2.0) | st.floats(2.0, 4.0)


@settings(max_examples=150, deadline=None)
@given(
    rung_age,
    reading | st.none(),
    st.floats(-1.0, 10.0) | st.none(),
    st.floats(-10.0, 10.0),
    speed,
    st.floats(-2.0, 2.0),
    st.floats(0.0, 20.0),
    st.floats(0.0, 5.0),
)
def test_member_rung_and_ladder_are_supervise(
    age: float,
    heard: tuple[float, float] | None,
    nearer: float | None,
    rate: float,
    v_cmd: float,
    dh_cmd: float,
    own_v: float,
    margin: float,
) -> None:
    """``_rung`` (with ``_overridden``) then ``_ladder`` against ``ConvoyMember.supervise``
    for follower 1, its predecessor's message ``age`` s old, a ranging reading or none and
    the predecessor's estimate or none (a ranged target ``nearer`` m closer than the
    estimate, at its own rate, where both exist)."""
    ranged = None if nearer is None else ((heard or (30.0, 0.0))[0] - nearer, rate)
    lad = LadderConfig(enabled=True, degrade_after_s=0.5, stop_after_s=2.0,
                       intruder_margin_m=margin)  # fmt: skip
    member = ConvoyMember(1, 2, MemberConfig(ladder=lad), lengths=[4.0, 4.5])
    now = 10.0
    member.observe_own(VehicleState(1, now, 0.0, 0.0, own_v, 0.0))
    member.receive(VehicleState(0, now - age, 20.0, 0.0, 5.0, 0.0), now - age)
    desired = member.spacing.pair_gap(own_v, 4.5, 4.0)
    frame = Frame(now, np.zeros(1, np.float32), desired_gap_m=desired, pred_gap=heard)
    action = np.array([v_cmd, dh_cmd], np.float32)
    want, want_mode = member.supervise(action, frame, ranged)

    m = _member([0], [now - age], lad, lengths=np.array([4.0, 4.5]),
                max_dh=MAX_HEADING_CHANGE_RAD)  # fmt: skip
    nan2 = (math.nan, math.nan)
    rng = np.array([[[math.nan, ranged[0] if ranged else math.nan]],
                    [[math.nan, ranged[1] if ranged else math.nan]]])  # fmt: skip
    est = np.array([[[math.nan, (heard or nan2)[0]]], [[math.nan, (heard or nan2)[1]]]])
    own = np.concatenate([_own(0.0, 0.0, 0.0, 0.0), _own(0.0, 0.0, own_v, 0.0)], axis=2)
    mode = vmember._rung(own, 0, 1, m, est, rng, now)
    v, dh, mode = vmember._ladder(
        own, 0, 1, m, est, rng, (float(action[0]), float(action[1]), mode)
    )
    assert ladder.MODES[mode] == want_mode
    assert (v, dh) == (float(want[0]), float(want[1]))


# A heard vehicle's newest message: (x m, y m, speed m/s, heading rad, age s), or unheard.
message = st.none() | st.tuples(
    st.floats(-60.0, 60.0), st.floats(-60.0, 60.0), speed, heading, st.floats(0.0, 4.0)
)


def _heard(member: ConvoyMember, msgs: list[tuple | None], now: float, first: int = 1) -> tuple:
    """Vehicle ``first + j``'s message ``msgs[j]`` (None: unheard) given to ``member`` and
    laid out as the kernels' R^i buffer, link ``j`` carrying that vehicle: (hist, hist_n)."""
    hist = np.zeros((1, len(msgs), 1, FIELDS))
    hist_n = np.zeros((1, len(msgs)), np.int64)
    for j, msg in enumerate(msgs):
        if msg is None:
            continue
        x, y, v, h, age = msg
        member.receive(VehicleState(first + j, now - age, x, y, v, h), now)
        hist[:, j] = _history(x, y, v, h, now - age)[:, 0]
        hist_n[0, j] = 1
    return hist, hist_n


@settings(max_examples=150, deadline=None)
@given(st.lists(message, min_size=1, max_size=4), coord, coord, speed, heading, positive)
def test_member_nearest_in_path_is_path_gap(
    msgs: list[tuple | None], x: float, y: float, v: float, h: float, decel: float
) -> None:
    """``lead_guard``'s ``_nearest_in_path`` against the leader's ``ConvoyMember.path_gap``:
    followers heard or not, anywhere around the leader."""
    n = len(msgs) + 1
    lengths = [4.0 + 0.5 * j for j in range(n)]
    decels = [decel * (1 + j) for j in range(n)]
    leader = ConvoyMember(0, n, MemberConfig(), lengths=lengths, decels=decels)
    now = 10.0
    leader.observe_own(VehicleState(0, now, x, y, v, h))
    hist, hist_n = _heard(leader, msgs, now)
    m = _member([-1], [-math.inf], LadderConfig(), hist=hist, hist_n=hist_n,
                link_decel=np.array(decels[1:]), lengths=np.array(lengths),
                lead_link=np.arange(-1, n - 1, dtype=np.int64),
                fresh_age=MemberConfig().rule_fresh_age_s)  # fmt: skip
    own = _own(x, y, v, h).repeat(n, axis=2)  # the followers' own rows are not read
    gap, closing, j = vmember._nearest_in_path(own, 0, m, now)
    want = leader.path_gap(now)
    assert (gap, closing, j) == HYPOT_ULP(want if want is not None else (math.inf, 0.0, -1))


@settings(max_examples=150, deadline=None)
@given(message, reading | st.none(), coord, coord, speed, heading, positive)
def test_member_rule_gap_is_gap_estimate(
    msg: tuple | None,
    ranged: tuple[float, float] | None,
    x: float,
    y: float,
    v: float,
    h: float,
    decel: float,
) -> None:
    """``decide``'s ``_rule_gap`` against ``ConvoyMember.gap_estimate`` (bumper to bumper
    by the two lengths), or the ranging reading where there is one (closing: the range
    rate negated), as ``ConvoyWorld._emergency`` reads them."""
    lengths, decels = [4.0, 4.5], [decel, 2.0 * decel]
    member = ConvoyMember(1, 2, MemberConfig(), lengths=lengths, decels=decels)
    now = 10.0
    member.observe_own(VehicleState(1, now, x, y, v, h))
    hist, hist_n = _heard(member, [msg], now, first=0)
    m = _member([0], [-math.inf], LadderConfig(), hist=hist, hist_n=hist_n,
                link_decel=np.array([decel]), lengths=np.array(lengths),
                fresh_age=MemberConfig().rule_fresh_age_s)  # fmt: skip
    rng = np.full((2, 1, 2), math.nan)
    if ranged is not None:
        rng[:, 0, 1] = ranged
    own = np.concatenate([_own(0.0, 0.0, 0.0, 0.0), _own(x, y, v, h)], axis=2)
    got = vmember._rule_gap(own, 0, 1, m, now, rng)
    if ranged is not None:
        want = (True, ranged[0] - 4.25, -ranged[1])
    else:
        est = member.gap_estimate(now)
        want = (False, 0.0, 0.0) if est is None else (True, est[0] - 4.25, est[1])
    assert got == HYPOT_ULP(want)


# The plant's twin (envs.vector.plant) against BicyclePlant, vehicle by vehicle.
_PRESETS = sorted(VEHICLE_PRESETS)  # lag and PI speed loops, delays of 0 to 3 steps


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(_PRESETS), st.floats(-1.0, 8.0), heading), min_size=1,
             max_size=3),
    st.lists(st.tuples(st.floats(-2.0, 12.0), st.floats(-0.6, 0.6)), min_size=1, max_size=40),
)  # fmt: skip
def test_plant_step_is_bicycle_plant_step(
    vehicles: list[tuple[str, float, float]], commands: list[tuple[float, float]]
) -> None:
    """``_plant_step`` (with ``_pi_dv``) against ``BicyclePlant.step``: the same presets
    placed at the same speeds and headings, then the same setpoints (every vehicle the
    same speed, a heading change of its own heading) tick by tick; every state row equal
    after every tick."""
    presets = [VEHICLE_PRESETS[name] for name, _, _ in vehicles]
    n = len(presets)
    x, y = np.arange(n) * 10.0, np.zeros(n)
    v0 = np.array([v for _, v, _ in vehicles])
    h0 = np.array([h for _, _, h in vehicles])
    ref = BicyclePlant(presets, 0.1)
    ref.reset(x, y, h0, v0)
    batched = vplant.VectorPlant(presets, 0.1)
    batched.reset_rows(np.arange(n), x, y, h0, v0)
    for k, (v_cmd, dh) in enumerate(commands):
        change = np.full(n, dh)
        absolute = [float(h) + dh for h in ref.heading]
        ref.step([v_cmd] * n, absolute)
        vplant._plant_step(batched.arrays, np.full(n, v_cmd), change, 0.1)
        for row, want in ((vplant.X, ref.x), (vplant.Y, ref.y), (SPEED, ref.speed),
                          (HEADING, ref.heading), (vplant.ACCEL, ref.accel),
                          (vplant.YAW_RATE, ref.yaw_rate)):  # fmt: skip
            assert list(batched.state[row]) == list(want), (k, row)


# The ranging twin (envs.vector.ranging) against ConvoyWorld's reading.
# on a centimetre grid: no distance so small its square underflows (``norm``'s range)
_vehicle = st.tuples(centimetres, centimetres, speed, heading)
_sensor = st.just((0.0, 0.0, 0.0)) | st.tuples(
    st.floats(1.0, 60.0), st.floats(0, 1), st.floats(0, 1)
)


@FAST
@given(st.lists(st.tuples(_vehicle, _sensor), min_size=2, max_size=4), u64, st.integers(0, 10**6))
def test_ranging_read_is_the_worlds_reading(
    vehicles: list[tuple[tuple, tuple]], key: int, tick: int
) -> None:
    """``_read`` against ``ConvoyWorld.ranging_readings``' arithmetic: ``core.ranging
    .range_and_rate`` to the vehicle ahead, none beyond the sensor's range (or without a
    sensor: max range 0), plus ``envs.ranging_noise.ranging_normals``' noise. The range is
    ``hypot``'s within an ulp (the kernels' ``norm``), so both within 1e-12 relative."""
    n = len(vehicles)
    own = np.zeros((ROWS, 1, n))
    for i, ((x, y, v, h), _) in enumerate(vehicles):
        own[[X, Y, SPEED, HEADING], 0, i] = x, y, v, h
    params = np.array([s for _, s in vehicles]).T.copy()
    out = np.zeros((2, 1, n))
    vranging._read(own, np.array([tick]), np.array([key], np.uint64), params, out)
    states = gps.vehicle_states(key, n)
    for i in range(1, n):
        max_range, sd_range, sd_rate = params[:, i]
        rng_m, rate = core_ranging.range_and_rate(*own[:4, 0, i], *own[:4, 0, i - 1])
        if max_range <= 0.0 or rng_m > max_range or rng_m <= 0.0:
            assert np.isnan(out[:, 0, i]).all()
            continue
        n1, n2 = ranging_normals(states[i], tick)
        want = (rng_m + sd_range * n1, rate + sd_rate * n2)
        assert out[:, 0, i] == pytest.approx(want, rel=1e-12, abs=1e-12)


# The measures' twins (envs.vector.measures) against ConvoyWorld.measure and envs.reward.
@FAST
@given(
    st.lists(
        st.tuples(
            centimetres, st.just(0.0) | centimetres, st.integers(50, 600).map(lambda k: k / 100)
        ),
        min_size=2,
        max_size=5,
    ),
)
@example([(0.0, 0.0, 4.0), (4.0, 0.0, 4.0)])  # touching: a gap of half the lengths
def test_measures_measure_is_the_worlds(vehicles: list[tuple[float, float, float]]) -> None:
    """Gaps (``hypot`` within an ulp: the kernels' ``norm``) and collisions (a gap under
    half the two lengths) as ``ConvoyWorld.measure`` takes them from the true state; on a
    centimetre grid and often in line, so that some gaps are exactly half the lengths."""
    n = len(vehicles)
    own = np.zeros((ROWS, 1, n))
    own[X, 0], own[Y, 0] = [v[0] for v in vehicles], [v[1] for v in vehicles]
    half_sum = np.array([0.5 * (vehicles[i - 1][2] + vehicles[i][2]) for i in range(1, n)])
    gap, collided = np.zeros((1, n - 1)), np.zeros((1, n - 1), bool)
    vmeasures.measure(own, half_sum, gap, collided)
    x, y = own[X, 0], own[Y, 0]
    for f in range(n - 1):
        want = math.hypot(x[f] - x[f + 1], y[f] - y[f + 1])
        assert abs(gap[0, f] - want) <= math.ulp(want)
        assert collided[0, f] == (want < half_sum[f])


_term = st.floats(-20.0, 20.0)


@FAST
@given(
    st.lists(st.tuples(gap, gap | st.just(math.nan), _term, _term, _term, st.booleans()),
             min_size=1, max_size=4),
    st.sampled_from([0.1, 0.05]),
)  # fmt: skip
def test_measures_reward_is_envs_reward(
    followers: list[tuple[float, float, float, float, float, bool]], dt: float
) -> None:
    """``reward`` against ``envs.reward.reward`` as ``ConvoyEnv.step`` calls it: the
    platooning error gap minus desired (NaN desired: no error), the jerk from the
    acceleration before and after the tick."""
    n = len(followers) + 1
    gaps = np.array([[f[0] for f in followers]])
    desired = np.array([[0.0] + [f[1] for f in followers]])
    accel_old = np.array([[0.0] + [f[2] for f in followers]])
    own = np.zeros((ROWS, 1, n))
    own[vplant.ACCEL, 0, 1:] = [f[3] for f in followers]
    own[vplant.YAW_RATE, 0, 1:] = [f[4] for f in followers]
    hit = np.array([[f[5] for f in followers]])
    config = RewardConfig(w_spacing=1.5, collision_penalty=50.0)
    out = np.zeros((1, n - 1))
    vmeasures.reward(out, gaps, desired, accel_old, own, hit, 1.0 / dt,
                     vmeasures.pack_reward(config))  # fmt: skip
    inv_dt = 1.0 / dt
    accel = own[vplant.ACCEL, 0, 1:].tolist()
    jerk = [(a1 - a0) * inv_dt for a0, a1 in zip(accel_old[0, 1:], accel, strict=True)]
    errors = [g - d for g, d in zip(gaps[0], desired[0, 1:], strict=True)]
    want = reward_mod.reward(
        config, errors, accel, jerk, own[vplant.YAW_RATE, 0, 1:].tolist(), hit[0].tolist()
    )
    assert out[0].tolist() == want


# followers mostly ahead of the leader (at the origin, heading east), near enough to fire
ahead_msg = st.none() | st.tuples(
    st.floats(-5.0, 40.0), st.floats(-4.0, 4.0), st.floats(0.0, 15.0), heading, st.floats(0, 0.5)
)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(ahead_msg, min_size=1, max_size=3),
    st.floats(0.0, 20.0),
    st.floats(-3.0, 3.0),
    st.floats(0.5, 8.0),
    st.tuples(st.floats(1.0, 8.0), st.floats(0.0, 1.0), st.floats(0.0, 5.0), st.floats(0, 0.5)),
)
def test_member_lead_guard_is_the_worlds_lead_emergency(
    msgs: list[tuple | None],
    v: float,
    accel: float,
    decel: float,
    rule: tuple[float, float, float, float],
) -> None:
    """``lead_guard`` against ``ConvoyWorld._lead_emergency``: the leader's
    ``ConvoyMember.path_gap``, bumper to bumper (``core.safety.bumper_gap``), through its
    ``BrakingGap`` against the braking limit of the member ahead; latched, the leader's
    command zeroed and the stop recorded."""
    n = len(msgs) + 1
    lengths = [4.0 + 3.0 * j for j in range(n)]  # unlike enough to tell apart
    decels = [decel * 4.0**-j for j in range(n)]
    leader = ConvoyMember(0, n, MemberConfig(), lengths=lengths, decels=decels)
    now = 10.0
    leader.observe_own(VehicleState(0, now, 0.0, 0.0, v, 0.0, accel))
    hist, hist_n = _heard(leader, msgs, now)
    m = _member([-1], [-math.inf], LadderConfig(), hist=hist, hist_n=hist_n,
                link_decel=np.array(decels[1:]), lengths=np.array(lengths),
                lead_link=np.arange(-1, n - 1, dtype=np.int64), decel=np.array(decels),
                fresh_age=MemberConfig().rule_fresh_age_s, lead_rule=np.array(rule),
                emergency=True)  # fmt: skip
    own = _own(0.0, 0.0, v, 0.0).repeat(n, axis=2)
    own[vplant.ACCEL, 0, 0] = accel
    out = vmember.Commands(
        np.zeros((1, n), np.int64), np.zeros((1, n), bool), np.zeros((1, n), bool),
        np.full((1, n), 7.0), np.full((1, n), 0.1), np.zeros((1, n), np.int64),
        np.full((len(vmember.EVENT_ROWS), 1, n), math.nan), np.zeros(1, np.int64),
    )  # fmt: skip
    vmember.lead_guard(np.array([now]), own, m, out)
    ahead = leader.path_gap(now)
    fires = ahead is not None and safety.BrakingGap(*rule).too_close(
        safety.bumper_gap(ahead[0], lengths[0], lengths[ahead[2]]), ahead[1], v,
        decels[ahead[2]], accel,
    )  # fmt: skip
    assert out.estopped[0, 0] == fires and out.n_events[0] == int(fires)
    if fires:
        assert (out.cmd_v[0, 0], out.cmd_dh[0, 0], out.modes[0, 0]) == (0.0, 0.0, vmember.FAILSAFE)
        assert out.events[vmember.ESTOP_T, 0, 0] == now
    else:
        assert (out.cmd_v[0, 0], out.cmd_dh[0, 0]) == (7.0, 0.1)
