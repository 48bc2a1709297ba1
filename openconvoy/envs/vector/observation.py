"""Observations, batched: ``ConvoyMember.observation`` (layout v1) for every follower of
every convoy in one compiled loop, with the targets' trail projections and the spacing
measures the env reports (desired gap, spacing error, predecessor age and estimate).

``geom`` packs the layout as (k, slot size, own offset, derived offset, path offset,
number of targets); ``LOOKAHEAD_S`` the path points' times.
"""

from __future__ import annotations

import math

import numpy as np

from openconvoy.core.observation import LOOKAHEAD_S, MAX_AGE_S, ObservationLayout
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, prefetch
from openconvoy.envs.vector.math import wrap
from openconvoy.envs.vector.member import estimate, link_age, pair_gap, speed_gap
from openconvoy.envs.vector.plant import ACCEL, HEADING, SPEED, YAW_RATE, X, Y, cos_sin
from openconvoy.envs.vector.trail import T_BASE, finish, head_s, point_at, project

LOOKAHEAD = np.array(LOOKAHEAD_S)
AHEAD = 4
"""Convoys ahead whose trails and states ``observe`` asks the cache for (``_warm``)."""
WARM_CRUMBS = 8
"""Breadcrumbs from the last projection's segment on that ``_warm`` fetches: the few the
projection walks (three cache lines). Fetching 24 (nine lines, for the path points a few
metres further) cost more than it saved: observe ran 0.91x / 0.86x as long with 8 at
B = 1,024 / 16,384 (tick-by-tick A/B in one process), 4 was slower at 16,384."""


def pack_layout(lay: ObservationLayout) -> np.ndarray:
    """The layout's sizes and offsets as the kernel's array."""
    return np.array(
        [lay.k, lay.slot_size, lay.own_offset, lay.derived_offset, lay.path_offset,
         len(lay.targets)], dtype=np.int64,
    )  # fmt: skip


@bare_inline
def _slots(obs, b, f, t, own, c, s, hist, hist_n, slot_link, geom):  # pragma: no cover
    """The state slots: each kept sender's last k states in the ego frame (``c``, ``s``:
    cosine and sine of the ego heading)."""
    i = f + 1
    ex, ey, eh = own[X, b, i], own[Y, b, i], own[HEADING, b, i]
    for k in range(slot_link.shape[1]):
        link = slot_link[f, k]
        if link < 0:
            continue
        for j in range(hist_n[b, link]):
            o = k * geom[1] + j * 7
            dx, dy = hist[b, link, j, 1] - ex, hist[b, link, j, 2] - ey
            obs[b, f, o] = c * dx + s * dy
            obs[b, f, o + 1] = c * dy - s * dx
            obs[b, f, o + 2] = wrap(hist[b, link, j, 4] - eh)
            obs[b, f, o + 3] = hist[b, link, j, 3]
            obs[b, f, o + 4] = hist[b, link, j, 5]
            obs[b, f, o + 5] = min(max(t - hist[b, link, j, 0], 0.0), MAX_AGE_S)
            obs[b, f, o + 6] = 1.0


@bare_inline
def _desired(f, m, ev, sp, lengths, F, lead):  # pragma: no cover - compiled
    """Desired arc gap (m) of follower ``f + 1`` to target ``m`` (0 leader, m pred_m),
    summed pair by pair in ``ConvoyMember``'s order (``lead``: the leader's under
    constant distance, the same sum carried from follower to follower)."""
    acc = 0.0
    if m == 0:
        if sp[0] == 0.0:
            return lead
        g = speed_gap(sp, ev)
        for q in range(f + 1):
            acc += g + 0.5 * (lengths[q + 1] + lengths[q])
        return acc
    for q in range(m):
        jj = min(max(f + 1 - m + q, 0), F - 1)
        acc = acc + pair_gap(sp, ev, lengths[jj + 1], lengths[jj])
    return acc


@bare_inline
def _path(
    obs, b, f, own, c, s, trail, tail, trail_n, tl, hx, hy, hh, cross, pheading, ps, o, guess
):  # pragma: no cover
    """The path features: cross track, heading error, lookahead points in the ego frame."""
    i = f + 1
    ex, ey, ev, eh = own[X, b, i], own[Y, b, i], own[SPEED, b, i], own[HEADING, b, i]
    obs[b, f, o] = -cross
    obs[b, f, o + 1] = wrap(pheading - eh)
    scale = max(1.0, abs(ev))
    s_head = head_s(tail, b, tl, hx, hy)
    for j in range(len(LOOKAHEAD)):
        px, py = point_at(
            trail, tail, trail_n, b, tl, hx, hy, hh, ps + LOOKAHEAD[j] * scale, guess, s_head
        )
        dx, dy = px - ex, py - ey
        obs[b, f, o + 2 + 2 * j] = c * dx + s * dy
        obs[b, f, o + 3 + 2 * j] = -s * dx + c * dy
    obs[b, f, o + 8] = 1.0


@bare_kernel
def observe(
    obs, rows, t, own, hist, hist_n, newest, trail, tail, trail_n, trail_of, hint, hint_k, slot_link,
    target_link, pred_link, link_decel, lengths, sp, stop_after, fresh_age, geom, desired_gap, spacing_error,
    pred_age, pred_est, tg,
):  # pragma: no cover - compiled  # fmt: skip
    """Fill ``obs`` (B, F, D) float32 for convoys ``rows`` and the spacing measures;
    ``tg`` (13, targets): scratch, per target: valid, x, y, speed, heading, arc, cross
    track × segment length, segment dx, s, desired, segment, segment dy, segment length
    (``project``'s; ``finish`` turns them into cross track and path heading)."""
    B, F = obs.shape[0], obs.shape[1]
    for b in range(B):
        if b + AHEAD < B and rows[b + AHEAD]:
            _warm(b + AHEAD, hist, trail, tail, trail_n, trail_of, hint_k, slot_link, target_link)
        if not rows[b]:
            continue
        tb = t[b]
        lead = 0.0  # the leader's desired gap under constant distance: sp[1] summed f + 1 times
        for f in range(F):
            i = f + 1
            lead += sp[1]
            obs[b, f, :] = 0.0
            c, s = cos_sin(own, b, i)
            _slots(obs, b, f, tb, own, c, s, hist, hist_n, slot_link, geom)
            ev = own[SPEED, b, i]
            o = geom[2]
            obs[b, f, o], obs[b, f, o + 1], obs[b, f, o + 2] = (
                ev,
                own[ACCEL, b, i],
                own[YAW_RATE, b, i],
            )
            desired_gap[b, i] = pair_gap(sp, ev, lengths[i], lengths[i - 1])
            age = link_age(newest, b, pred_link[f], tb) if pred_link[f] >= 0 else np.inf
            pred_age[b, i] = np.nan if math.isinf(age) else age
            chosen = _targets(obs, tg, b, f, tb, own, hist, hist_n, trail, tail, trail_n,
                              trail_of, hint, hint_k, target_link, link_decel, lengths, sp, stop_after, fresh_age,
                              geom, F, lead)  # fmt: skip
            spacing_error[b, i] = np.nan
            pred_est[0, b, i], pred_est[1, b, i] = np.nan, np.nan
            if chosen < 0:
                continue
            err = tg[5, chosen] - tg[9, chosen]
            spacing_error[b, i] = np.float64(np.float32(err))
            if chosen == 1:
                pred_est[0, b, i], pred_est[1, b, i] = tg[5, 1], tg[3, 1] - ev
            cross, pheading = finish(tg[6, chosen], tg[7, chosen], tg[11, chosen],
                                     tg[12, chosen], tg[4, chosen])  # fmt: skip
            _path(obs, b, f, own, c, s, trail, tail, trail_n, trail_of[target_link[f, chosen]],
                  tg[1, chosen], tg[2, chosen], tg[4, chosen], cross, pheading, tg[8, chosen],
                  geom[4], int(tg[10, chosen]) + 1)  # fmt: skip


@bare_inline
def _warm(
    b, hist, trail, tail, trail_n, trail_of, hint_k, slot_link, target_link
):  # pragma: no cover
    """Prefetch what ``observe`` will read of convoy ``b``: its followers' slot states and
    the target trails around the last projections. Only a hint to the cache: without
    it, each convoy's first reads wait on memory in turn."""
    F = slot_link.shape[0]
    for f in range(F):
        for k in range(slot_link.shape[1]):
            link = slot_link[f, k]
            if link >= 0:
                for j in range(hist.shape[2]):
                    prefetch(hist, b, link, j, 0)
        for m in range(target_link.shape[1]):
            link = target_link[f, m]
            if link < 0:
                continue
            tl = trail_of[link]
            lo = hint_k[b, tl]
            hi = min(lo + WARM_CRUMBS, trail_n[b, tl])
            w = trail.shape[2]
            base = int(tail[b, tl, T_BASE])
            for j in range(lo, hi, 2):  # two breadcrumbs (48 bytes): every cache line
                prefetch(trail, b, tl, (base + j) & (w - 1), 0)


@bare_inline
def _targets(
    obs, tg, b, f, t, own, hist, hist_n, trail, tail, trail_n, trail_of, hint, hint_k,
    target_link, link_decel, lengths, sp, stop_after, fresh_age, geom, F, lead,
):  # pragma: no cover - compiled  # fmt: skip
    """Estimate and project every target of follower ``f + 1`` (results in ``tg``), write
    the derived features; returns the nearest heard target (pred_1..pred_M, then the
    leader) or -1."""
    i = f + 1
    ex, ey, ev = own[X, b, i], own[Y, b, i], own[SPEED, b, i]
    ntg = tg.shape[1]
    chosen = -1
    for m in range(ntg):
        link = target_link[f, m]
        valid, hx, hy, hv, hh, _ = estimate(
            hist, hist_n, link_decel, b, link, t, stop_after, fresh_age
        )
        tg[0, m] = 1.0 if valid else 0.0
        if not valid:
            continue
        tg[1, m], tg[2, m], tg[3, m], tg[4, m] = hx, hy, hv, hh
        desired = _desired(f, m, ev, sp, lengths, F, lead)
        tl = trail_of[link]
        arc, s, k, cross_seg, dx, dy, seg = project(
            trail, tail, trail_n, b, tl, hx, hy, hh, ex, ey, desired, hint[b, tl], hint_k[b, tl]
        )
        hint[b, tl], hint_k[b, tl] = s, max(k, 0)
        tg[5, m], tg[6, m], tg[7, m], tg[8, m] = arc, cross_seg, dx, s
        tg[11, m], tg[12, m] = dy, seg
        o = geom[3] + m * 5
        obs[b, f, o], obs[b, f, o + 1], obs[b, f, o + 2] = arc, desired, arc - desired
        obs[b, f, o + 3], obs[b, f, o + 4] = hv, 1.0
        tg[9, m], tg[10, m] = desired, max(k, 0)
        if m >= 1 and chosen < 0:
            chosen = m
    if chosen < 0 and tg[0, 0] != 0.0:
        chosen = 0
    return chosen
