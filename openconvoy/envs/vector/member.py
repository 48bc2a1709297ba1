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

import numpy as np

from openconvoy.core import safety, spacing
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.member import PATH_CONE
from openconvoy.core.spacing import SpacingConfig
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules
from openconvoy.envs.vector.math import cos_sin, norm

rules(spacing, "time_headway_gap_m", "speed_gap_m", "pair_gap_m")
rules(safety, "gap_reduction_m")

COOP, DEGRADED, STOP, FAILSAFE = range(4)
EVENT_ROWS = ("error_t_s", "error_speed", "error_change", "estop_t_s", "estop_bumper_m",
              "estop_closing_mps", "estop_ego_mps", "estop_pred_decel", "estop_ego_accel")  # fmt: skip
"""``decide``'s event record, per vehicle and episode (NaN until it happens): when the
first refused action came and its two values; when the emergency stop latched, with the
bumper gap, closing speed, own speed, the braking limit of the vehicle ahead and own
acceleration it read."""


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
    none); inf when none."""
    return max(0.0, t - newest[b, ln])


@bare_inline
def estimate(hist, hist_n, link_decel, b, ln, t, stop_after, fresh_age):  # pragma: no cover
    """``ConvoyMember.estimate`` of link ``ln``'s sender (``ln`` < 0: none):
    (valid, x m, y m, speed m/s, heading rad, age s). Fresh: dead-reckoned at its speed;
    stale: braking at its limit since the message."""
    li = ln if ln >= 0 else 0
    lt, lx, ly = hist[b, li, 0, 0], hist[b, li, 0, 1], hist[b, li, 0, 2]
    lv, lh = hist[b, li, 0, 3], hist[b, li, 0, 4]
    age = max(t - lt, 0.0)
    if not (ln >= 0 and hist_n[b, li] > 0 and not age > stop_after):
        return False, 0.0, 0.0, 0.0, 0.0, age  # invalid: the rest is never read
    if age <= fresh_age:
        d, speed = lv * age, lv
    else:
        a = link_decel[li]
        d, speed = 0.0, 0.0
        if lv > 0.0 and not math.isinf(a):
            tau = min(age, lv / a)
            d = lv * tau - 0.5 * a * tau * tau
            speed = max(lv - a * age, 0.0)
    if d == 0.0:  # not moved since the message: no trigonometry
        return True, lx + d, ly + d, speed, lh, age
    # the heading's cosine and sine as pushed (vector_rx): libm's of the same heading
    return True, lx + d * hist[b, li, 0, 6], ly + d * hist[b, li, 0, 7], speed, lh, age


@bare_kernel
def decide(
    act, low, high, t, own, hist, hist_n, newest, needed, pred_link, link_decel, lengths, sp, lad,
    fresh_age, max_dh, pred_est, errors, failed, estopped, emergency, rule, cmd_v, cmd_dh, modes,
    ranging, events, n_events, decel,
):  # pragma: no cover - compiled  # fmt: skip
    """One tick of ``core.tick.decide`` for every follower: the action (non-finite: a
    latched policy error), clipped and float32, through the ladder (with the ranging
    reading), then the latch and the emergency rule; writes ``cmd_v``, ``cmd_dh`` (B, N)
    and ``modes``. A latch that ``ConvoyWorld`` records in ``safety_events`` is written
    to ``events`` (``EVENT_ROWS``, (9, B, N)) and counted in ``n_events`` (B,).
    ``fresh_age``: the rule's (``MemberConfig.rule_fresh_age_s``); ``decel`` (N,) each
    vehicle's braking limit."""
    B, F = act.shape[0], act.shape[1]
    for b in range(B):
        for f in range(F):
            i = f + 1
            a0, a1 = act[b, f, 0], act[b, f, 1]
            if not (np.isfinite(a0) and np.isfinite(a1)):
                errors[b, i] += 1
                if not failed[b, i]:  # the first refusal of the episode: an event
                    events[0, b, i], events[1, b, i], events[2, b, i] = t[b], a0, a1
                    n_events[b] += 1
                failed[b, i] = True
                a0, a1 = np.float32(0.0), np.float32(0.0)
            v = float(np.float32(min(max(np.float64(a0), low[f, 0]), high[f, 0])))
            dh = float(np.float32(min(max(np.float64(a1), low[f, 1]), high[f, 1])))
            mode = COOP
            if lad[0] != 0.0:
                age = 0.0
                for ln in needed[i]:
                    if ln >= 0:
                        age = max(age, link_age(newest, b, ln, t[b]))
                mode = COOP if age <= lad[1] else (DEGRADED if age <= lad[2] else STOP)
                if mode == COOP and _overridden(own, b, i, lengths, sp, lad, pred_est, ranging):
                    mode = DEGRADED
                v, dh, mode = _ladder(own, b, i, lengths, sp, lad, pred_est, ranging, v, dh,
                                      mode, max_dh)  # fmt: skip
            if failed[b, i]:
                v, dh, mode = 0.0, 0.0, FAILSAFE
            if emergency:
                if _fires(own, b, i, hist, hist_n, pred_link[f], link_decel, lengths, lad,
                          fresh_age, rule[:, f], t[b], ranging, decel[i - 1]) or estopped[b, i]:  # fmt: skip
                    if not (estopped[b, i] or failed[b, i]):  # it latches: an event
                        # (a failed follower's rule is not consulted in ConvoyWorld: no event)
                        _record_stop(own, b, i, hist, hist_n, pred_link[f], link_decel, lengths,
                                     lad, fresh_age, t[b], ranging, events, n_events,
                                     decel[i - 1])  # fmt: skip
                    estopped[b, i] = True
                    v, dh, mode = 0.0, 0.0, FAILSAFE
            cmd_v[b, i], cmd_dh[b, i], modes[b, i] = v, dh, mode


@bare_inline
def _overridden(own, b, i, lengths, sp, lad, pred_est, ranging):  # pragma: no cover
    """``ConvoyMember._ranging_override``: the ranging target is closer by the intruder
    margin than the predecessor by its messages or the desired gap."""
    rng_m, v2v_gap = ranging[0, b, i], pred_est[0, b, i]
    if math.isnan(rng_m) or math.isnan(v2v_gap):
        return False
    desired = pair_gap(sp, own[2, b, i], lengths[i], lengths[i - 1])
    return rng_m < max(v2v_gap, desired) - lad[5]


@bare_inline
def _ladder(
    own, b, i, lengths, sp, lad, pred_est, ranging, v, dh, mode, max_dh
):  # pragma: no cover
    """``ConvoyMember.supervise``'s rungs: degraded follows the ACC fallback on the
    ranging reading, else the predecessor estimate (neither: stop), stop commands zero."""
    if mode == DEGRADED:
        est_gap, est_closing = pred_est[0, b, i], pred_est[1, b, i]
        if not math.isnan(ranging[0, b, i]):
            est_gap, est_closing = ranging[0, b, i], ranging[1, b, i]
        if math.isnan(est_gap):
            mode = STOP
        else:
            ego_v = own[2, b, i]
            target = pair_gap(sp, ego_v, lengths[i], lengths[i - 1]) + lad[3] * max(ego_v, 0.0)
            acc_v = max(0.0, ego_v + est_closing + lad[4] * (est_gap - target))
            v = float(np.float32(min(v, acc_v)))
            dh = float(np.float32(min(max(dh, -max_dh), max_dh)))
    if mode == STOP:
        v, dh = 0.0, 0.0
    return v, dh, mode


@bare_inline
def _rule_gap(
    own, b, i, hist, hist_n, link, link_decel, lengths, lad, fresh_age, t, ranging
):  # pragma: no cover - compiled
    """What the braking-aware gap rule reads: (known, bumper gap m, closing speed m/s),
    from the ranging reading, else from the estimate of the predecessor."""
    if not math.isnan(ranging[0, b, i]):
        gap, closing = ranging[0, b, i], -ranging[1, b, i]
    else:
        # no stop age: a predecessor silent for longer is still no further than braking at
        # its limit takes it (``ConvoyMember.gap_estimate``)
        # ``fresh_age``: the rule's (``MemberConfig.rule_fresh_age_s``, ``gap_estimate``)
        valid, ex, ey, es, _, _ = estimate(hist, hist_n, link_decel, b, link, t, np.inf, fresh_age)
        if not valid:
            return False, 0.0, 0.0
        # the estimate's heading is the message's: its cosine and sine as pushed (vector_rx)
        gap, closing = _gap_and_closing(own, b, i, ex, ey, es, hist[b, link, 0, 6],
                                        hist[b, link, 0, 7])  # fmt: skip
    return True, gap - 0.5 * (lengths[i] + lengths[i - 1]), closing


@bare_kernel
def _record_stop(
    own, b, i, hist, hist_n, link, link_decel, lengths, lad, fresh_age, t, ranging, events,
    n_events, pred_decel,
):  # pragma: no cover - compiled  # fmt: skip
    """An emergency stop latched at ``t``: its time and what the rule read, into
    ``events`` (``EVENT_ROWS`` 3-7). Out of line: the rare branch keeps the loop small."""
    _, bumper, closing = _rule_gap(own, b, i, hist, hist_n, link, link_decel, lengths, lad,
                                   fresh_age, t, ranging)  # fmt: skip
    events[3, b, i], events[4, b, i], events[5, b, i] = t, bumper, closing
    events[6, b, i], events[7, b, i], events[8, b, i] = own[2, b, i], pred_decel, own[4, b, i]
    n_events[b] += 1


@bare_inline
def _fires(
    own, b, i, hist, hist_n, link, link_decel, lengths, lad, fresh_age, rule, t, ranging,
    pred_decel,
):  # pragma: no cover - compiled  # fmt: skip
    """The braking-aware gap rule on ``_rule_gap``'s reading: True to stop."""
    known, bumper, closing = _rule_gap(own, b, i, hist, hist_n, link, link_decel, lengths, lad,
                                       fresh_age, t, ranging)  # fmt: skip
    if not known:
        return False
    return _too_close(bumper, closing, own[2, b, i], pred_decel, own[4, b, i], rule)


@bare_inline
def _too_close(bumper, closing, ego, pred_decel, accel, rule):  # pragma: no cover - compiled
    """``BrakingGap.too_close`` with the ego's speed: the rule ``(decel, reaction,
    margin, lag)`` on the bumper gap (m), closing speed (m/s), own speed (m/s) and the braking
    limit of the vehicle ahead (m/s²), and the own acceleration (m/s²)."""
    if not np.isfinite(bumper):
        return False
    if not np.isfinite(closing):
        closing = 0.0
    if not np.isfinite(ego):
        ego, pred = closing, 0.0
    else:
        pred = ego - closing
    reduction = safety.gap_reduction_m(ego, pred, rule[1], rule[3], rule[0], pred_decel, accel)
    return bumper - reduction < rule[2]


@bare_kernel
def lead_guard(
    t, own, hist, hist_n, lead_link, link_decel, decel, lengths, fresh_age, rule, estopped,
    emergency, cmd_v, cmd_dh, modes, events, n_events,
):  # pragma: no cover - compiled  # fmt: skip
    """``ConvoyWorld._lead_emergency`` for every leader: the braking rule ``rule`` (3,) to
    the nearest member in its path (``ConvoyMember.path_gap``; ``lead_link[j]``: the
    leader's link from vehicle ``j``, -1: none), latched; after the leader's command."""
    if not emergency:
        return
    B, N = own.shape[1], own.shape[2]
    for b in range(B):
        if not estopped[b, 0]:
            co, so = cos_sin(own, b, 0)
            best, best_closing, best_j = np.inf, 0.0, -1
            for j in range(1, N):
                ln = lead_link[j]
                if ln < 0:
                    continue
                valid, ex, ey, es, _, _ = estimate(hist, hist_n, link_decel, b, ln, t[b], np.inf,
                                                   fresh_age)  # fmt: skip
                if not valid:
                    continue
                dx, dy = ex - own[0, b, 0], ey - own[1, b, 0]
                half = 0.5 * (lengths[0] + lengths[j])
                along = co * dx + so * dy
                if not (along > 0.0 and abs(co * dy - so * dx) < half + PATH_CONE * along):
                    continue
                gap, closing = _gap_and_closing(own, b, 0, ex, ey, es, hist[b, ln, 0, 6],
                                                hist[b, ln, 0, 7])  # fmt: skip
                if best_j < 0 or gap < best:
                    best, best_closing, best_j = gap, closing, j
            if best_j < 0:
                continue
            bumper = best - 0.5 * (lengths[0] + lengths[best_j])
            if not _too_close(bumper, best_closing, own[2, b, 0], decel[best_j], own[4, b, 0],
                              rule):  # fmt: skip
                continue
            estopped[b, 0] = True
            events[3, b, 0], events[4, b, 0], events[5, b, 0] = t[b], bumper, best_closing
            events[6, b, 0], events[7, b, 0], events[8, b, 0] = (
                own[2, b, 0],
                decel[best_j],
                own[4, b, 0],
            )
            n_events[b] += 1
        cmd_v[b, 0], cmd_dh[b, 0], modes[b, 0] = 0.0, 0.0, FAILSAFE


@bare_inline
def _gap_and_closing(own, b, i, ex, ey, es, ce, se):  # pragma: no cover - compiled
    """``core.estimate.gap_and_closing`` of vehicle ``i`` to the estimate (x, y, speed,
    and its heading's cosine and sine): centre-to-centre gap (m) and closing speed (m/s,
    positive = closing)."""
    ox, oy, ov = own[0, b, i], own[1, b, i], own[2, b, i]
    co, so = cos_sin(own, b, i)
    dx, dy = ex - ox, ey - oy
    gap = norm(dx, dy)
    vx = ov * co - es * ce
    vy = ov * so - es * se
    if gap <= 0.0:
        return 0.0, max(ov - es, 0.0)
    return gap, (dx * vx + dy * vy) / gap
