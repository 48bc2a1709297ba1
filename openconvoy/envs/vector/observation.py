"""Observations, batched: ``ConvoyMember.observation`` (layout v1) for every follower of
every convoy in one compiled loop, with the targets' trail projections and the spacing
measures the env reports (desired gap, spacing error, predecessor age and estimate).

``geom`` packs the layout as (k, slot size, own offset, derived offset, path offset,
number of targets); ``LOOKAHEAD_S`` the path points' times. ``observe`` reads its
sources as one ``Sources`` and writes the measures into one ``Measures``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from openconvoy.core import observation as layout
from openconvoy.core.observation import LOOKAHEAD_S, ObservationLayout
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, prefetch, prefetch_row, rules
from openconvoy.envs.vector.math import wrap
from openconvoy.envs.vector.member import estimate, link_age, pair_gap, speed_gap
from openconvoy.envs.vector.plant import ACCEL, HEADING, SPEED, YAW_RATE, X, Y, cos_sin
from openconvoy.envs.vector.trail import T_BASE, finish, point_at, project_head

rules(layout, "to_ego", "ego_state")
LOOKAHEAD = np.array(LOOKAHEAD_S)
TG_ROWS = 14
"""Rows of ``Measures.tg``, the per-target scratch."""
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


class Sources(NamedTuple):
    """What ``observe`` reads besides the tick's arrays (arrays filled in place; built
    again when the trails' rings widen, ``VectorConvoyEnv._observed``): the R^i buffers ``hist``, ``hist_n``, ``newest`` and the trails
    ``trail``, ``tail``, ``trail_n`` (``vector.rx``), the projection hints ``hint``,
    ``hint_k`` (read and written); the link tables ``trail_of``, ``slot_link``,
    ``target_link``, ``pred_link`` (``vector.links``); each link's sender's braking limit
    (m/s²), the lengths (m), the packed ``spacing``; the ladder's stop age and the fresh
    age (s); the layout's ``geom`` (``pack_layout``)."""

    hist: np.ndarray
    hist_n: np.ndarray
    newest: np.ndarray
    trail: np.ndarray
    tail: np.ndarray
    trail_n: np.ndarray
    hint: np.ndarray
    hint_k: np.ndarray
    trail_of: np.ndarray
    slot_link: np.ndarray
    target_link: np.ndarray
    pred_link: np.ndarray
    link_decel: np.ndarray
    lengths: np.ndarray
    spacing: np.ndarray
    stop_after: float
    fresh_age: float
    geom: np.ndarray


class Measures(NamedTuple):
    """What ``observe`` writes besides the observations, (B, N): the desired gap and
    spacing error (m), the predecessor's message age (s), its estimate (2, B, N: arc to
    its head, m; closing, m/s); and the per-target scratch ``tg`` (``TG_ROWS``, targets):
    valid, x, y, speed, heading, arc, cross track × segment length, segment dx, s,
    desired, segment, segment dy, segment length (``project``'s; ``finish`` turns them
    into cross track and path heading), the head's arc coordinate (``head_s``)."""

    desired_gap: np.ndarray
    spacing_error: np.ndarray
    pred_age: np.ndarray
    pred_est: np.ndarray
    tg: np.ndarray


@bare_inline
def _slots(obs, b, f, t, own, src):  # pragma: no cover
    """Twin of ``ConvoyMember.observation``'s state slots: each kept sender's last k
    states in the ego frame (``core.observation.ego_state``, compiled). Property-tested
    through ``observe``: tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step."""
    i = f + 1
    c, s = cos_sin(own, b, i)
    ex, ey, eh = own[X, b, i], own[Y, b, i], own[HEADING, b, i]
    hist, slot_link = src.hist, src.slot_link
    for k in range(slot_link.shape[1]):
        link = slot_link[f, k]
        if link < 0:
            continue
        for j in range(src.hist_n[b, link]):
            o = k * src.geom[1] + j * 7
            x, y, dh, age = layout.ego_state(
                c, s, hist[b, link, j, 1] - ex, hist[b, link, j, 2] - ey,
                hist[b, link, j, 4] - eh, t - hist[b, link, j, 0],
            )  # fmt: skip
            obs[b, f, o], obs[b, f, o + 1], obs[b, f, o + 2] = x, y, dh
            obs[b, f, o + 3], obs[b, f, o + 4] = hist[b, link, j, 3], hist[b, link, j, 5]
            obs[b, f, o + 5], obs[b, f, o + 6] = age, 1.0


@bare_inline
def _desired(f, m, ev, sp, lengths, F, lead):  # pragma: no cover - compiled
    """Twin of ``GapChain.gap_to``: desired arc gap (m) of follower ``f + 1`` to target
    ``m`` (0 leader, m pred_m), summed pair by pair in ``ConvoyMember``'s order (``lead``: the leader's under
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
def _path(obs, b, f, own, src, tg, m):  # pragma: no cover
    """Twin of ``core.member.fill_path``: the path features of follower ``f + 1`` along
    target ``m``'s trail (its estimate and projection in ``tg``): cross track, heading
    error, lookahead points in the ego frame. Property-tested through ``observe``:
    tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step."""
    i = f + 1
    c, s = cos_sin(own, b, i)
    cross, pheading = finish(tg[6, m], tg[7, m], tg[11, m], tg[12, m], tg[4, m])
    tl = src.trail_of[src.target_link[f, m]]
    hx, hy, hh, ps, guess = tg[1, m], tg[2, m], tg[4, m], tg[8, m], int(tg[10, m]) + 1
    trail, tail, trail_n = src.trail, src.tail, src.trail_n
    o = src.geom[4]
    ex, ey, ev, eh = own[X, b, i], own[Y, b, i], own[SPEED, b, i], own[HEADING, b, i]
    obs[b, f, o] = -cross
    obs[b, f, o + 1] = wrap(pheading - eh)
    scale = max(1.0, abs(ev))
    s_head = tg[13, m]  # head_s, as the projection computed it
    for j in range(len(LOOKAHEAD)):
        px, py = point_at(
            trail, tail, trail_n, b, tl, hx, hy, hh, ps + LOOKAHEAD[j] * scale, guess, s_head
        )
        obs[b, f, o + 2 + 2 * j], obs[b, f, o + 3 + 2 * j] = layout.to_ego(c, s, px - ex, py - ey)
    obs[b, f, o + 8] = 1.0


@bare_kernel
def observe(obs, rows, t, own, src, out):  # pragma: no cover - compiled
    """Twin of ``ConvoyMember.observation`` (with ``ConvoyMember.sense``'s logged
    measures) for every follower: fill ``obs`` (B, F, D) float32 for convoys ``rows`` and
    the spacing measures ``out`` (``Measures``) from ``src`` (``Sources``)."""
    B, F = obs.shape[0], obs.shape[1]
    tg = out.tg
    for b in range(B):
        if b + 2 * AHEAD < B:
            _warm_tails(b + 2 * AHEAD, src)
        if b + AHEAD < B and rows[b + AHEAD]:
            _warm(b + AHEAD, src)
        if not rows[b]:
            continue
        tb = t[b]
        lead = 0.0  # the leader's desired gap under constant distance: sp[1] summed f + 1 times
        for f in range(F):
            i = f + 1
            lead += src.spacing[1]
            obs[b, f, :] = 0.0
            _slots(obs, b, f, tb, own, src)
            ev = own[SPEED, b, i]
            o = src.geom[2]
            obs[b, f, o], obs[b, f, o + 1], obs[b, f, o + 2] = (
                ev,
                own[ACCEL, b, i],
                own[YAW_RATE, b, i],
            )
            out.desired_gap[b, i] = pair_gap(src.spacing, ev, src.lengths[i], src.lengths[i - 1])
            pred = src.pred_link[f]
            age = link_age(src.newest, b, pred, tb) if pred >= 0 else np.inf
            out.pred_age[b, i] = np.nan if math.isinf(age) else age
            chosen = _targets(obs, tg, b, f, tb, own, src, lead)
            out.spacing_error[b, i] = np.nan
            out.pred_est[0, b, i], out.pred_est[1, b, i] = np.nan, np.nan
            if chosen < 0:
                continue
            err = tg[5, chosen] - tg[9, chosen]
            out.spacing_error[b, i] = np.float64(np.float32(err))
            if chosen == 1:
                out.pred_est[0, b, i], out.pred_est[1, b, i] = tg[5, 1], tg[3, 1] - ev
            _path(obs, b, f, own, src, tg, chosen)


@bare_inline
def _warm_tails(b, src):  # pragma: no cover
    """Prefetch convoy ``b``'s trail tails (their first line: the ring's base) and
    projection hints: what ``_warm`` reads, ``AHEAD`` convoys later, to find the
    breadcrumbs to fetch (its reads would otherwise wait on memory). No value of its own
    (held with ``observe``:
    tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step)."""
    for tl in range(src.tail.shape[1]):
        prefetch_row(src.tail, b, tl)
    prefetch_row(src.hint_k, b, 0)
    prefetch_row(src.trail_n, b, 0)


@bare_inline
def _warm(b, src):  # pragma: no cover
    """Prefetch what ``observe`` will read of convoy ``b`` (``ConvoyMember.observation``'s
    reads, no value of its own): its followers' slot states and the target trails around
    the last projections. Only a hint to the cache: without it, each convoy's first reads
    wait on memory in turn. That it changes nothing is held with ``observe``:
    tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step."""
    hist, trail, slot_link, target_link = src.hist, src.trail, src.slot_link, src.target_link
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
            tl = src.trail_of[link]
            lo = src.hint_k[b, tl]
            hi = min(lo + WARM_CRUMBS, src.trail_n[b, tl])
            w = trail.shape[2]
            base = int(src.tail[b, tl, T_BASE])
            for j in range(lo, hi, 2):  # two breadcrumbs (48 bytes): every cache line
                prefetch(trail, b, tl, (base + j) & (w - 1), 0)


@bare_inline
def _targets(obs, tg, b, f, t, own, src, lead):  # pragma: no cover - compiled
    """Twin of ``ConvoyMember._fill_targets``: estimate and project every target of
    follower ``f + 1`` (results in ``tg``), write the derived features
    (tests/envs/vector/test_twins_step.py::test_fused_step_and_its_stages_are_convoy_env_step); returns the nearest heard target (pred_1..pred_M, then the
    leader) or -1."""
    i = f + 1
    ex, ey, ev = own[X, b, i], own[Y, b, i], own[SPEED, b, i]
    F = obs.shape[1]
    hint, hint_k = src.hint, src.hint_k
    ntg = tg.shape[1]
    chosen = -1
    for m in range(ntg):
        link = src.target_link[f, m]
        valid, hx, hy, hv, hh, _ = estimate(
            src.hist, src.hist_n, src.link_decel, b, link, t, src.stop_after, src.fresh_age
        )
        tg[0, m] = 1.0 if valid else 0.0
        if not valid:
            continue
        tg[1, m], tg[2, m], tg[3, m], tg[4, m] = hx, hy, hv, hh
        desired = _desired(f, m, ev, src.spacing, src.lengths, F, lead)
        tl = src.trail_of[link]
        arc, s, k, cross_seg, dx, dy, seg, s_head = project_head(
            src.trail, src.tail, src.trail_n, b, tl, hx, hy, hh, ex, ey, desired,
            hint[b, tl], hint_k[b, tl],
        )  # fmt: skip
        hint[b, tl], hint_k[b, tl] = s, max(k, 0)
        tg[5, m], tg[6, m], tg[7, m], tg[8, m] = arc, cross_seg, dx, s
        tg[11, m], tg[12, m] = dy, seg
        o = src.geom[3] + m * 5
        obs[b, f, o], obs[b, f, o + 1], obs[b, f, o + 2] = arc, desired, arc - desired
        obs[b, f, o + 3], obs[b, f, o + 4] = hv, 1.0
        tg[9, m], tg[10, m], tg[13, m] = desired, max(k, 0), s_head
        if m >= 1 and chosen < 0:
            chosen = m
    if chosen < 0 and tg[0, 0] != 0.0:
        chosen = 0
    return chosen
