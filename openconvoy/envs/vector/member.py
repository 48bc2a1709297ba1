"""The member's decisions, batched: ``ConvoyMember.estimate``, the staleness ladder
(``supervise``), the policy-error latch and the braking-aware emergency stop, for every
follower of every convoy in one compiled loop.

``spacing`` packs ``SpacingConfig`` as (kind code, distance m, standstill m, headway s,
quadratic s²/m); ``ladder`` packs ``LadderConfig`` as (enabled, degrade after s, stop
after s, extra headway s, gap gain 1/s, intruder margin m); ``rule`` the emergency rule
per follower as (decel m/s², reaction s, margin m, lag s); ``ranging`` (2, B, N) each vehicle's
ranging reading this tick (range m, range rate m/s; NaN range: none, ``vector.ranging``),
which the ladder's ACC fallback, the ranging override and the emergency rule take
before the estimate from messages (``ConvoyMember.supervise``, ``ConvoyWorld._emergency``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from openconvoy.core import estimate as estimate_mod
from openconvoy.core import ladder, safety, spacing
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.member import PATH_CONE
from openconvoy.core.spacing import SpacingConfig
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules
from openconvoy.envs.vector.plant import ACCEL, SPEED, X, Y, cos_sin
from openconvoy.envs.vector.rx import HC, HH, HS, HV, HX, HY, T

rules(spacing, "time_headway_gap_m", "speed_gap_m", "pair_gap_m")
rules(safety, "gap_reduction_m", "stopping_distance_m", "too_close", "verdict")
rules(estimate_mod, "reckoned_travel", "closing_m")
rules(ladder, "rung_code", "intruder_closer", "acc_speed_mps")

COOP, DEGRADED, STOP, FAILSAFE = range(4)  # core.ladder.rung_code's, then the latches'
ENABLED, DEGRADE_AFTER, STOP_AFTER, EXTRA_HEADWAY, GAP_GAIN, INTRUDER_MARGIN = range(6)
"""Rows of ``pack_ladder``'s array."""
RANGE, RATE = range(2)
"""Rows of a ranging reading and of ``pred_est``: range or gap (m), its rate (m/s)."""
EVENT_ROWS = ("error_t_s", "error_speed", "error_change", "estop_t_s", "estop_bumper_m",
              "estop_closing_mps", "estop_ego_mps", "estop_pred_decel", "estop_ego_accel")  # fmt: skip
"""``decide``'s event record, per vehicle and episode (NaN until it happens): when the
first refused action came and its two values; when the emergency stop latched, with the
bumper gap, closing speed, own speed, the braking limit of the vehicle ahead and own
acceleration it read."""
ERROR_T, ERROR_SPEED, ERROR_CHANGE, ESTOP_T = range(4)


def pack_spacing(c: SpacingConfig) -> np.ndarray:
    """``SpacingConfig`` as the kernels' array."""
    kind = float(c.code)
    return np.array([kind, c.distance_m, c.standstill_m, c.headway_s, c.quadratic_s2_per_m])


def pack_ladder(c: LadderConfig) -> np.ndarray:
    """``LadderConfig`` as the kernels' array."""
    return np.array(
        [
            float(c.enabled),
            c.degrade_after_s,
            c.stop_after_s,
            c.extra_headway_s,
            c.gap_gain,
            c.intruder_margin_m,
        ]
    )


@bare_inline
def speed_gap(sp, v):  # pragma: no cover - compiled
    """``core.spacing.speed_gap_m`` at ``v`` (m/s) for the packed config ``sp``."""
    return spacing.speed_gap_m(int(sp[0]), v, sp[2], sp[3], sp[4])


@bare_inline
def pair_gap(sp, v, len_behind, len_ahead):  # pragma: no cover - compiled
    """``core.spacing.pair_gap_m``: the desired centre-to-centre gap (m) of a vehicle to
    the one ahead at speed ``v``, for the packed config ``sp``."""
    half = 0.5 * (len_behind + len_ahead)
    return spacing.pair_gap_m(int(sp[0]), v, sp[1], sp[2], sp[3], sp[4], half)


@bare_inline
def link_age(newest, b, ln, t):  # pragma: no cover - compiled
    """Age (s) of link ``ln``'s newest message at ``t`` (``newest``: its time, -inf when
    none); inf when none: one link's term of ``ConvoyMember.needed_age``."""
    return max(0.0, t - newest[b, ln])


@bare_inline
def estimate(hist, hist_n, link_decel, b, ln, t, stop_after, fresh_age):  # pragma: no cover
    """``ConvoyMember.estimate`` of link ``ln``'s sender (``ln`` < 0: none):
    (valid, x m, y m, speed m/s, heading rad, age s). Fresh: dead-reckoned at its speed;
    stale: braking at its limit since the message."""
    li = ln if ln >= 0 else 0
    lt, lx, ly = hist[b, li, 0, T], hist[b, li, 0, HX], hist[b, li, 0, HY]
    lv, lh = hist[b, li, 0, HV], hist[b, li, 0, HH]
    age = max(t - lt, 0.0)
    if not (ln >= 0 and hist_n[b, li] > 0 and not age > stop_after):
        return False, 0.0, 0.0, 0.0, 0.0, age  # invalid: the rest is never read
    d, speed = estimate_mod.reckoned_travel(lv, age, fresh_age, link_decel[li])
    if d == 0.0:  # not moved since the message: no trigonometry
        return True, lx + d, ly + d, speed, lh, age
    # the heading's cosine and sine as pushed (vector_rx): libm's of the same heading
    return True, lx + d * hist[b, li, 0, HC], ly + d * hist[b, li, 0, HS], speed, lh, age


class Member(NamedTuple):
    """What ``decide`` and ``lead_guard`` read besides the tick's arrays, fixed for an
    env's life (arrays filled in place): the action bounds ``low``, ``high`` (F, 2); the
    R^i buffers ``hist``, ``hist_n``, ``newest`` (``vector.rx``); the links each follower
    needs, its predecessor's and the leader's from each vehicle (``vector.links``, -1:
    none); each link's sender's and each vehicle's braking limit (m/s²); the lengths (m);
    the packed ``spacing`` and ``ladder``; the rule's fresh age (s); the heading clip
    (rad); the emergency rules (4, F) and the leader's (4,); emergency stops on or off."""

    low: np.ndarray
    high: np.ndarray
    hist: np.ndarray
    hist_n: np.ndarray
    newest: np.ndarray
    needed: np.ndarray
    pred_link: np.ndarray
    lead_link: np.ndarray
    link_decel: np.ndarray
    decel: np.ndarray
    lengths: np.ndarray
    spacing: np.ndarray
    ladder: np.ndarray
    fresh_age: float
    max_dh: float
    rule: np.ndarray
    lead_rule: np.ndarray
    emergency: bool


class Commands(NamedTuple):
    """What ``decide`` and ``lead_guard`` write, (B, N) unless said: the policy-error
    count and latch, the emergency latch, the commanded speed (m/s), heading change (rad)
    and mode, the event record (``EVENT_ROWS``, B, N) and its count (B,)."""

    errors: np.ndarray
    failed: np.ndarray
    estopped: np.ndarray
    cmd_v: np.ndarray
    cmd_dh: np.ndarray
    modes: np.ndarray
    events: np.ndarray
    n_events: np.ndarray


@bare_kernel
def decide(act, t, own, ranging, pred_est, m, out):  # pragma: no cover - compiled
    """One tick of ``core.tick.decide`` for every follower: the action ``act`` (B, F, 2;
    non-finite: a latched policy error), clipped and float32, through the ladder (with the
    ``ranging`` reading and the predecessor estimate ``pred_est``), then the latch and the
    emergency rule; ``m`` a ``Member``, writes ``out`` (``Commands``). A latch that
    ``ConvoyWorld`` records in ``safety_events`` is written to its event record.
    Property-tested through ``fused_step``:
    tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step."""
    B, F = act.shape[0], act.shape[1]
    for b in range(B):
        for f in range(F):
            i = f + 1
            a0, a1 = act[b, f, 0], act[b, f, 1]
            if not (np.isfinite(a0) and np.isfinite(a1)):
                out.errors[b, i] += 1
                if not out.failed[b, i]:  # the first refusal of the episode: an event
                    out.events[ERROR_T, b, i] = t[b]
                    out.events[ERROR_SPEED, b, i], out.events[ERROR_CHANGE, b, i] = a0, a1
                    out.n_events[b] += 1
                out.failed[b, i] = True
                a0, a1 = np.float32(0.0), np.float32(0.0)
            v = float(np.float32(min(max(np.float64(a0), m.low[f, 0]), m.high[f, 0])))
            dh = float(np.float32(min(max(np.float64(a1), m.low[f, 1]), m.high[f, 1])))
            mode = COOP
            if m.ladder[ENABLED] != 0.0:
                mode = _rung(own, b, i, m, pred_est, ranging, t[b])
                v, dh, mode = _ladder(own, b, i, m, pred_est, ranging, (v, dh, mode))
            if out.failed[b, i]:
                v, dh, mode = 0.0, 0.0, FAILSAFE
            if m.emergency and not out.failed[b, i]:
                # (a failed follower's rule is not consulted in ConvoyWorld)
                rule = (
                    safety.TOO_CLOSE
                    if out.estopped[b, i]
                    else _verdict(own, b, i, m, t[b], ranging)
                )
                if rule == safety.TOO_CLOSE:
                    if not out.estopped[b, i]:  # it latches: an event
                        _record_stop(own, b, i, m, t[b], ranging, out)
                    out.estopped[b, i] = True
                    v, dh, mode = 0.0, 0.0, FAILSAFE
                elif rule == safety.BLIND:  # the predecessor unheard: brake (not latched)
                    v, dh, mode = 0.0, 0.0, STOP
            out.cmd_v[b, i], out.cmd_dh[b, i], out.modes[b, i] = v, dh, mode


@bare_inline
def _rung(own, b, i, m, pred_est, ranging, t):  # pragma: no cover - compiled
    """``core.ladder.rung`` on the oldest needed message at ``t``, then the ranging
    override (``ConvoyMember.supervise``): the mode code."""
    age = 0.0
    for ln in m.needed[i]:
        if ln >= 0:
            age = max(age, link_age(m.newest, b, ln, t))
    mode = ladder.rung_code(age, m.ladder[DEGRADE_AFTER], m.ladder[STOP_AFTER])
    if mode == COOP and _overridden(own, b, i, m, pred_est, ranging):
        return DEGRADED
    return mode


@bare_inline
def _overridden(own, b, i, m, pred_est, ranging):  # pragma: no cover - compiled
    """``ConvoyMember._ranging_override``: the ranging target is closer by the intruder
    margin than the predecessor by its messages or the desired gap. Property-tested with
    ``_rung``: tests/envs/vector/test_twins.py::test_member_rung_and_ladder_are_supervise."""
    rng_m, v2v_gap = ranging[RANGE, b, i], pred_est[RANGE, b, i]
    if math.isnan(rng_m) or math.isnan(v2v_gap):
        return False
    desired = pair_gap(m.spacing, own[SPEED, b, i], m.lengths[i], m.lengths[i - 1])
    return ladder.intruder_closer(rng_m, v2v_gap, desired, m.ladder[INTRUDER_MARGIN])


@bare_inline
def _ladder(own, b, i, m, pred_est, ranging, command):  # pragma: no cover - compiled
    """``ConvoyMember.supervise``'s rungs on ``command`` (speed, heading change, mode):
    degraded follows the ACC fallback on the ranging reading, else the predecessor
    estimate (neither: stop), stop commands zero."""
    v, dh, mode = command
    if mode == DEGRADED:
        est_gap, est_closing = pred_est[RANGE, b, i], pred_est[RATE, b, i]
        if not math.isnan(ranging[RANGE, b, i]):
            est_gap, est_closing = ranging[RANGE, b, i], ranging[RATE, b, i]
        if math.isnan(est_gap):
            mode = STOP
        else:
            ego_v = own[SPEED, b, i]
            desired = pair_gap(m.spacing, ego_v, m.lengths[i], m.lengths[i - 1])
            lad = m.ladder
            acc_v = ladder.acc_speed_mps(
                est_gap, est_closing, ego_v, desired, lad[EXTRA_HEADWAY], lad[GAP_GAIN]
            )
            v = float(np.float32(min(v, acc_v)))
            dh = float(np.float32(min(max(dh, -m.max_dh), m.max_dh)))
    if mode == STOP:
        v, dh = 0.0, 0.0
    return v, dh, mode


@bare_inline
def _rule_gap(own, b, i, m, t, ranging):  # pragma: no cover - compiled
    """What the braking-aware gap rule reads (``ConvoyWorld._emergency``): (known, bumper
    gap m, closing speed m/s), from the ranging reading, else from the estimate of the
    predecessor (``ConvoyMember.gap_estimate``)."""
    if not math.isnan(ranging[RANGE, b, i]):
        gap, closing = ranging[RANGE, b, i], -ranging[RATE, b, i]
    else:
        # no stop age: a predecessor silent for longer is still no further than braking at
        # its limit takes it (``ConvoyMember.gap_estimate``); the fresh age is the rule's
        # (``MemberConfig.rule_fresh_age_s``)
        link = m.pred_link[i - 1]
        valid, ex, ey, es, _, _ = estimate(
            m.hist, m.hist_n, m.link_decel, b, link, t, np.inf, m.fresh_age
        )
        if not valid:
            return False, 0.0, 0.0
        # the estimate's heading is the message's: its cosine and sine as pushed (vector_rx)
        ce, se = m.hist[b, link, 0, HC], m.hist[b, link, 0, HS]
        gap, closing = _gap_and_closing(own, b, i, ex, ey, es, ce, se)
    return True, gap - 0.5 * (m.lengths[i] + m.lengths[i - 1]), closing


@bare_kernel
def _record_stop(own, b, i, m, t, ranging, out):  # pragma: no cover - compiled
    """An emergency stop latched at ``t``: its time and what the rule read, into the
    event record. Out of line: the rare branch keeps the loop small."""
    _, bumper, closing = _rule_gap(own, b, i, m, t, ranging)
    _record(out, b, i, (t, bumper, closing, own[SPEED, b, i], m.decel[i - 1], own[ACCEL, b, i]))


@bare_inline
def _record(out, b, i, read):  # pragma: no cover - compiled
    """Twin of ``ConvoyWorld._rule_fires``' record of an emergency stop: vehicle ``i``'s
    into the event record, ``read`` being (time s, bumper gap m, closing m/s, own speed
    m/s, braking limit ahead m/s², own acceleration m/s²), what the world's event text
    (``BrakingRule.reason``) is made of."""
    for k in range(6):
        out.events[ESTOP_T + k, b, i] = read[k]
    out.n_events[b] += 1


@bare_inline
def _verdict(own, b, i, m, t, ranging):  # pragma: no cover - compiled
    """The braking-aware gap rule on ``_rule_gap``'s reading (``core.safety.verdict``)."""
    known, bumper, closing = _rule_gap(own, b, i, m, t, ranging)
    ego, accel = own[SPEED, b, i], own[ACCEL, b, i]
    return safety.verdict(known, bumper, closing, ego, m.decel[i - 1], accel, m.rule[:, i - 1])


@bare_kernel
def lead_guard(t, own, m, out):  # pragma: no cover - compiled
    """``ConvoyWorld._lead_emergency`` for every leader: its braking rule ``m.lead_rule``
    to the nearest member in its path (``ConvoyMember.path_gap``), latched; after the
    leader's command. ``m`` a ``Member``, writes ``out`` (``Commands``)."""
    if not m.emergency:
        return
    for b in range(own.shape[1]):
        if not out.estopped[b, 0]:
            best, closing, j = _nearest_in_path(own, b, m, t[b])
            if j < 0:
                continue
            bumper = best - 0.5 * (m.lengths[0] + m.lengths[j])
            ego, accel = own[SPEED, b, 0], own[ACCEL, b, 0]
            if not safety.too_close(bumper, closing, ego, m.decel[j], accel, m.lead_rule):
                continue
            out.estopped[b, 0] = True
            _record(out, b, 0, (t[b], bumper, closing, ego, m.decel[j], accel))
        out.cmd_v[b, 0], out.cmd_dh[b, 0], out.modes[b, 0] = 0.0, 0.0, FAILSAFE


@bare_inline
def _nearest_in_path(own, b, m, t):  # pragma: no cover - compiled
    """The nearest member in the leader's path by its estimate (``ConvoyMember.path_gap``):
    (centre gap m, closing speed m/s, vehicle; -1: none)."""
    co, so = cos_sin(own, b, 0)
    best, best_closing, best_j = np.inf, 0.0, -1
    for j in range(1, own.shape[2]):
        ln = m.lead_link[j]
        if ln < 0:
            continue
        valid, ex, ey, es, _, _ = estimate(
            m.hist, m.hist_n, m.link_decel, b, ln, t, np.inf, m.fresh_age
        )
        if not valid:
            continue
        dx, dy = ex - own[X, b, 0], ey - own[Y, b, 0]
        half = 0.5 * (m.lengths[0] + m.lengths[j])
        along = co * dx + so * dy
        if not (along > 0.0 and abs(co * dy - so * dx) < half + PATH_CONE * along):
            continue
        ce, se = m.hist[b, ln, 0, HC], m.hist[b, ln, 0, HS]
        gap, closing = _gap_and_closing(own, b, 0, ex, ey, es, ce, se)
        if best_j < 0 or gap < best:
            best, best_closing, best_j = gap, closing, j
    return best, best_closing, best_j


@bare_inline
def _gap_and_closing(own, b, i, ex, ey, es, ce, se):  # pragma: no cover - compiled
    """``core.estimate.gap_and_closing`` of vehicle ``i`` to the estimate (x, y, speed,
    and its heading's cosine and sine): centre-to-centre gap (m) and closing speed (m/s,
    positive = closing)."""
    ov = own[SPEED, b, i]
    co, so = cos_sin(own, b, i)
    dvx, dvy = ov * co - es * ce, ov * so - es * se
    return estimate_mod.closing_m(ex - own[X, b, i], ey - own[Y, b, i], dvx, dvy, ov, es)
