"""Trails as ring arrays: ``core.trail.Trail``'s add, project and point_at, compiled.

A trail is ``n[b, ln]`` breadcrumbs, x, y (m) and arc coordinate s (m), at most
``CAPACITY``, the oldest half dropped when full, as ``Trail``. Row ``(b, ln)`` of ``tr``
(B, T, W, 3) holds the newest ``W`` of them in a ring (breadcrumb ``k``, 0 the oldest, at
``(base + k) % W``): W is sized to the horizon the observation reads (``window``), not to
the capacity, so a trail's memory and the pages a tick touches stay small; reads older
than the ring (``crumb``) get the oldest two from ``tail`` and, for a search, an arc
coordinate below the ring's. The env widens the ring before a read could need more
(``T_REACH``). (A fourth field, each segment's heading laid once instead of an atan2 per
query, measured slower: more cache lines per query.) ``tail[b, ln]`` (``TAIL``,) is its
newest breadcrumb again, the smoothed fix x, y, t, the ring's base and the reach (one cache
line: what every add and query reads), then what only reads behind the newest breadcrumb
need (``T_S0``...). A query's path is the
extension behind the oldest breadcrumb, the breadcrumbs, and the head ``(hx, hy)`` with
heading ``hh`` (the sender's dead-reckoned position): the same vertices, segments and
walk as ``Trail``, so the same numbers.
"""

from __future__ import annotations

import math

from openconvoy.core.trail import SMOOTHING
from openconvoy.envs.vector.jit import bare_inline
from openconvoy.envs.vector.math import norm

CAPACITY = 1024
"""Breadcrumbs per trail, as ``core.trail.Trail`` (the oldest half dropped when full)."""
MIN_WINDOW = 16
"""Fewest breadcrumbs a ring holds (``window``)."""
T_FIX, T_BASE, T_REACH = 3, 6, 7
"""``tail`` fields, the first line's (read or written every tick; 0-2 the newest breadcrumb):
the smoothed fix x, y, t (3-5), the ring's base (the oldest breadcrumb's count since the
reset) and the reach (the most breadcrumbs back from the newest a projection read; the
path points lie ahead of it)."""
T_S0, T_BACK, T_OLD, T_NEXT = 8, 9, 11, 16
"""``tail`` fields read only behind the newest breadcrumb: the oldest one's arc coordinate,
the unit vector behind it (NaN once it was dropped), the oldest two breadcrumbs (x0, y0,
x1, y1, s1) and the two laid at ``CAPACITY // 2`` and after (x, y, s each: the oldest two
after the next drop)."""
TAIL = 24
"""Fields of ``tail`` (22 used): three cache lines a trail, the hot fields in the first
(``RxBuffers`` aligns the rows)."""


def window(horizon_m: float, spacing_m: float, step_m: float) -> int:
    """Ring size (breadcrumbs, a power of two in ``MIN_WINDOW..CAPACITY``) for reads up to
    ``horizon_m`` behind the head, breadcrumbs ``spacing_m`` apart and senders moving at
    most ``step_m`` a tick: the horizon within 3/4 of the ring (``needs_wider``), and a
    tick's progress within the rest."""
    need = max(horizon_m / spacing_m * 4.0 / 3.0, 4.0 * step_m / spacing_m, MIN_WINDOW)
    w = MIN_WINDOW
    while w < need and w < CAPACITY:
        w *= 2
    return w


def needs_wider(reach: float, w: int) -> bool:
    """Whether a ring of ``w`` with reads ``reach`` breadcrumbs back must widen before the
    next tick: a tick moves a read back by less than a quarter ring (``window``), so reads
    within 3/4 of it stay inside it."""
    return w < CAPACITY and reach > 0.75 * w


@bare_inline
def crumb(tr, tail, b, ln, n, k, f):  # pragma: no cover - compiled
    """Twin of ``Trail._vertex`` for breadcrumbs (``0 <= k < n``): field ``f`` (0 x, 1 y,
    2 s) of breadcrumb ``k`` (0 the oldest of ``n``) of trail ``(b, ln)``: from the ring while it holds it, the oldest two from ``tail``; older
    ones s = -inf (below every s in the ring, where a search's answer is), x, y NaN
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    w = tr.shape[2]
    if n - k <= w:
        return tr[b, ln, (int(tail[b, ln, T_BASE]) + k) & (w - 1), f]
    if k == 0:
        return tail[b, ln, T_S0] if f == 2 else tail[b, ln, T_OLD + f]
    if k == 1:
        return tail[b, ln, T_OLD + 4] if f == 2 else tail[b, ln, T_OLD + 2 + f]
    return -math.inf if f == 2 else math.nan


@bare_inline
def _reach(tail, b, ln, n, k):  # pragma: no cover - compiled
    """Record a read of breadcrumb ``k`` (and its neighbours) of ``n``: the ring's
    bookkeeping for ``Trail.project``'s walk (no value of its own; the ring is widened
    before a read could miss it)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    r = n - k + 2
    if r > tail[b, ln, T_REACH]:
        tail[b, ln, T_REACH] = r


FAR_M = 1e4
"""Length of the straight extension behind the oldest breadcrumb (``Trail._vertex``)."""


@bare_inline
def trail_add(tr, tail, n, b, ln, x, y, spacing, t, v, c, sn):  # pragma: no cover - compiled
    """``Trail.add`` with the sender's time ``t`` (s), speed ``v`` (m/s) and heading's
    cosine and sine: (x, y) smoothed along the reported motion (``tail`` ``T_FIX``: the smoothed
    fix and its time), laid ``spacing`` m of progress along the heading after the last
    breadcrumb."""
    nn = n[b, ln]
    if nn > 0:
        d = v * (t - tail[b, ln, T_FIX + 2])
        px, py = tail[b, ln, T_FIX] + d * c, tail[b, ln, T_FIX + 1] + d * sn
        x, y = px + SMOOTHING * (x - px), py + SMOOTHING * (y - py)
    tail[b, ln, T_FIX], tail[b, ln, T_FIX + 1], tail[b, ln, T_FIX + 2] = x, y, t
    step = 0.0
    ps = 0.0
    if nn > 0:
        if (x - tail[b, ln, 0]) * c + (y - tail[b, ln, 1]) * sn < spacing:
            return
        ps = tail[b, ln, 2]
        step = norm(x - tail[b, ln, 0], y - tail[b, ln, 1])
        if step < spacing:
            return
    half = CAPACITY // 2
    if nn >= CAPACITY:  # drop the oldest half: the ring's base moves, nothing is copied
        nn -= half
        tail[b, ln, T_BASE] += half
        tail[b, ln, T_S0] = tail[b, ln, T_NEXT + 2]
        for f in range(2):
            tail[b, ln, T_OLD + f] = tail[b, ln, T_NEXT + f]
            tail[b, ln, T_OLD + 2 + f] = tail[b, ln, T_NEXT + 3 + f]
        tail[b, ln, T_OLD + 4] = tail[b, ln, T_NEXT + 5]
        tail[b, ln, T_BACK] = math.nan  # the oldest breadcrumb's heading is gone
    s = ps + step if nn > 0 else 0.0
    w = tr.shape[2]
    slot = (int(tail[b, ln, T_BASE]) + nn) & (w - 1)
    tr[b, ln, slot, 0], tr[b, ln, slot, 1], tr[b, ln, slot, 2] = x, y, s
    tail[b, ln, 0], tail[b, ln, 1], tail[b, ln, 2] = x, y, s
    if nn == 0:
        tail[b, ln, T_S0] = s
        tail[b, ln, T_BACK], tail[b, ln, T_BACK + 1] = -c, -sn
    if nn <= 1:  # the oldest two, kept past the ring
        tail[b, ln, T_OLD + 2 * nn], tail[b, ln, T_OLD + 2 * nn + 1] = x, y
        if nn == 1:
            tail[b, ln, T_OLD + 4] = s
    elif nn == half or nn == half + 1:  # the oldest two after the next drop
        o = T_NEXT + 3 * (nn - half)
        tail[b, ln, o], tail[b, ln, o + 1], tail[b, ln, o + 2] = x, y, s
    n[b, ln] = nn + 1


@bare_inline
def _bisect(tr, tail, b, ln, n, value, guess):  # pragma: no cover - compiled
    """Twin of ``bisect.bisect_right`` (as ``Trail.project`` and ``Trail.point_at`` call
    it) of ``value`` in the trail's arc coordinates, searched outwards
    from index ``guess`` (exact for any guess; a few reads for a good one: a vehicle
    moves a little along a trail per tick)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    g = min(max(guess, 0), n)
    if g < n and crumb(tr, tail, b, ln, n, g, 2) <= value:  # the answer is above g
        lo, step = g + 1, 1
        hi = lo + step
        while hi < n and crumb(tr, tail, b, ln, n, hi, 2) <= value:
            lo, step = hi + 1, step * 2
            hi = lo + step
        hi = min(hi, n)
    elif g > 0 and value < crumb(tr, tail, b, ln, n, g - 1, 2):  # the answer is below g
        hi, step = g - 1, 1
        lo = hi - step
        while lo > 0 and value < crumb(tr, tail, b, ln, n, lo - 1, 2):
            hi, step = lo - 1, step * 2
            lo = hi - step
        lo = max(lo, 0)
    else:
        return g
    while lo < hi:
        mid = (lo + hi) >> 1
        if value < crumb(tr, tail, b, ln, n, mid, 2):
            hi = mid
        else:
            lo = mid + 1
    return lo


@bare_inline
def _back(tr, tail, b, ln, n, hx, hy, hh):  # pragma: no cover - compiled
    """``Trail._back_direction``: unit vector backwards from the oldest breadcrumb
    (against the heading reported there: ``tail`` ``T_BACK``, NaN once it was dropped)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    if not math.isnan(tail[b, ln, T_BACK]):
        return tail[b, ln, T_BACK], tail[b, ln, T_BACK + 1]
    x0, y0 = tail[b, ln, T_OLD], tail[b, ln, T_OLD + 1]
    if n >= 2:
        dx, dy = tail[b, ln, T_OLD + 2] - x0, tail[b, ln, T_OLD + 3] - y0
    else:
        dx, dy = hx - x0, hy - y0
    d = norm(dx, dy)
    if d < 1e-9:
        return -math.cos(hh), -math.sin(hh)
    return -dx / d, -dy / d


@bare_inline
def _vertex(tr, tail, b, ln, n, k, hx, hy, hh, s_head):  # pragma: no cover - compiled
    """``Trail._vertex``: -1 the far end of the extension, 0..n-1 breadcrumbs, n the head
    (at arc coordinate ``s_head``)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    if k >= n:
        return hx, hy, s_head
    if k >= 0:
        return (
            crumb(tr, tail, b, ln, n, k, 0),
            crumb(tr, tail, b, ln, n, k, 1),
            crumb(tr, tail, b, ln, n, k, 2),
        )
    bx, by = _back(tr, tail, b, ln, n, hx, hy, hh)
    x0, y0, s0 = tail[b, ln, T_OLD], tail[b, ln, T_OLD + 1], tail[b, ln, T_S0]
    return x0 + FAR_M * bx, y0 + FAR_M * by, s0 - FAR_M


@bare_inline
def _segment(tr, tail, b, ln, n, k, hx, hy, hh, s_head, x, y):  # pragma: no cover - compiled
    """``Trail._segment`` of (x, y) on segment k -> k+1: (dist², s, dx, dy, seg, rx, ry),
    the cross track and heading left to ``_finish`` (only the nearest needs them)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    ax, ay, sa = _vertex(tr, tail, b, ln, n, k, hx, hy, hh, s_head)
    bx, by, sb = _vertex(tr, tail, b, ln, n, k + 1, hx, hy, hh, s_head)
    dx, dy = bx - ax, by - ay
    seg = norm(dx, dy)
    rx, ry = x - ax, y - ay
    if seg < 1e-12:
        return rx * rx + ry * ry, sa, dx, dy, seg, rx, ry
    u = min(max((rx * dx + ry * dy) / (seg * seg), 0.0), 1.0)
    ex, ey = rx - u * dx, ry - u * dy
    return ex * ex + ey * ey, sa + u * (sb - sa), dx, dy, seg, rx, ry


@bare_inline
def _dist2(tr, tail, b, ln, n, k, hx, hy, hh, s_head, x, y):  # pragma: no cover - compiled
    """Twin of ``core.trail._segment_dist2`` (``Trail.project``'s walk): ``_segment``'s
    squared distance alone, the same bits: where the clamp of ``u`` to
    0 or 1 is certain (the point before the segment's start, or well past its end, as
    the walk's neighbours mostly are) without the sqrt and the division
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    ax, ay, _ = _vertex(tr, tail, b, ln, n, k, hx, hy, hh, s_head)
    bx, by, _ = _vertex(tr, tail, b, ln, n, k + 1, hx, hy, hh, s_head)
    dx, dy = bx - ax, by - ay
    rx, ry = x - ax, y - ay
    dot = rx * dx + ry * dy
    if dot <= 0.0:  # u = 0, or a degenerate segment: the distance to a either way
        return rx * rx + ry * ry
    q = dx * dx + dy * dy
    # seg >= 1e-12 and dot / (seg * seg) > 1 for certain (seg * seg is q within 3 ulps): u = 1
    if q > 2e-24 and dot > q * (1.0 + 1e-12):
        ex, ey = rx - dx, ry - dy
        return ex * ex + ey * ey
    seg = norm(dx, dy)
    if seg < 1e-12:
        return rx * rx + ry * ry
    u = min(max(dot / (seg * seg), 0.0), 1.0)
    ex, ey = rx - u * dx, ry - u * dy
    return ex * ex + ey * ey


@bare_inline
def project(tr, tail, n_arr, b, ln, hx, hy, hh, x, y, expected, hint, hint_k):  # pragma: no cover
    """``Trail.project`` from ``hint`` (NaN: ``expected`` m behind the head; ``hint_k``
    where to look for it): (arc to head, s, segment, cross track × seg, dx, dy, seg); the
    cross track and path heading from the last four by ``finish`` (only the target the
    observation uses needs them: an atan2 and a division saved for the others)."""
    arc, s, k, cross_seg, dx, dy, seg, _ = project_head(
        tr, tail, n_arr, b, ln, hx, hy, hh, x, y, expected, hint, hint_k
    )
    return arc, s, k, cross_seg, dx, dy, seg


@bare_inline
def project_head(
    tr, tail, n_arr, b, ln, hx, hy, hh, x, y, expected, hint, hint_k
):  # pragma: no cover
    """``project``, and the head's arc coordinate (m), ``head_s``'s value, as the last
    item: the path points after a projection need it, and its square root is a tenth of
    the observation's latency chain (the same expression: the same bits)."""
    n = n_arr[b, ln]
    to_head = norm(hx - tail[b, ln, 0], hy - tail[b, ln, 1])
    last = n - 1 if to_head > 1e-9 else n - 2
    s_head = tail[b, ln, 2] + to_head
    start = s_head - expected if math.isnan(hint) else hint
    k = min(max(_bisect(tr, tail, b, ln, n, start, hint_k + 1) - 1, -1), last)
    near = _segment(tr, tail, b, ln, n, k, hx, hy, hh, s_head, x, y)
    best, k0 = near[0], k
    # Trail.project's walk: forwards while closer, then backwards while closer. Both
    # neighbours are evaluated at once (independent: they overlap; out of range they
    # are still defined, and unused). Once the walk has moved forwards, its first step
    # back is onto a segment it left for a closer one, so it stops there. The walk
    # compares distances only (the start's projection kept: the walk seldom moves).
    fwd = _dist2(tr, tail, b, ln, n, k + 1, hx, hy, hh, s_head, x, y)
    bwd = _dist2(tr, tail, b, ln, n, k - 1, hx, hy, hh, s_head, x, y)
    if k + 1 <= last and fwd < best:
        best, k = fwd, k + 1
        j = k + 1
        while j <= last:
            cand = _dist2(tr, tail, b, ln, n, j, hx, hy, hh, s_head, x, y)
            if cand >= best:
                break
            best, k = cand, j
            j += 1
    elif k - 1 >= -1 and bwd < best:
        best, k = bwd, k - 1
        j = k - 1
        while j >= -1:
            cand = _dist2(tr, tail, b, ln, n, j, hx, hy, hh, s_head, x, y)
            if cand >= best:
                break
            best, k = cand, j
            j -= 1
    if k != k0:
        near = _segment(tr, tail, b, ln, n, k, hx, hy, hh, s_head, x, y)
    _, s, dx, dy, seg, rx, ry = near
    _reach(tail, b, ln, n, k)
    return s_head - s, s, k, dx * ry - dy * rx, dx, dy, seg, s_head


@bare_inline
def finish(cross_seg, dx, dy, seg, hh):  # pragma: no cover - compiled
    """A ``project`` result's cross track (m) and path heading (rad; ``hh``, the head's
    heading, on a degenerate segment), as ``Trail._segment``."""
    if seg < 1e-12:
        return 0.0, hh
    return cross_seg / seg, math.atan2(dy, dx)


@bare_inline
def head_s(tail, b, ln, hx, hy):  # pragma: no cover - compiled
    """Twin of ``Trail.head_s``: the head's arc coordinate (m) on trail ``(b, ln)`` with
    the head at (hx, hy)
    (tests/envs/vector/test_twins.py::test_the_ring_trail_projects_and_reads_as_trail)."""
    return tail[b, ln, 2] + norm(hx - tail[b, ln, 0], hy - tail[b, ln, 1])


@bare_inline
def point_at(tr, tail, n_arr, b, ln, hx, hy, hh, s, guess, s_head):  # pragma: no cover
    """``Trail.point_at``: the path point at arc coordinate ``s`` (beyond the head: on);
    ``guess``: a breadcrumb index near it; ``s_head``: ``head_s`` (once per query head)."""
    n = n_arr[b, ln]
    lx, ly, ls = tail[b, ln, 0], tail[b, ln, 1], tail[b, ln, 2]
    if s >= s_head and not s_head - ls > 1e-9:
        return hx + (s - s_head) * math.cos(hh), hy + (s - s_head) * math.sin(hh)
    if s >= ls:
        f = (s - ls) / (s_head - ls)
        return lx + f * (hx - lx), ly + f * (hy - ly)
    s0 = tail[b, ln, T_S0]
    if s <= s0:
        bx, by = _back(tr, tail, b, ln, n, hx, hy, hh)
        return tail[b, ln, T_OLD] - (s - s0) * bx, tail[b, ln, T_OLD + 1] - (s - s0) * by
    # (no _reach: the path points lie ahead of the projection, whose read is recorded)
    i = min(max(_bisect(tr, tail, b, ln, n, s, guess) - 1, 0), max(n - 2, 0))
    xi, yi, si = (
        crumb(tr, tail, b, ln, n, i, 0),
        crumb(tr, tail, b, ln, n, i, 1),
        crumb(tr, tail, b, ln, n, i, 2),
    )
    xj, yj, sj = (
        crumb(tr, tail, b, ln, n, i + 1, 0),
        crumb(tr, tail, b, ln, n, i + 1, 1),
        crumb(tr, tail, b, ln, n, i + 1, 2),
    )
    f = (s - si) / (sj - si)
    return xi + f * (xj - xi), yi + f * (yj - yi)
