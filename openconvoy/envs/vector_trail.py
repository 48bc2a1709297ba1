"""Trails as ring arrays: ``core.trail.Trail``'s add, project and point_at, compiled.

A trail is row ``(b, ln)`` of ``tr`` (3, B, L, C): breadcrumb x, y (m) and arc coordinate
s (m), ``n[b, ln]`` of them, the oldest half dropped when full. A query's path is the
extension behind the oldest breadcrumb, the breadcrumbs, and the head ``(hx, hy)`` with
heading ``hh`` (the sender's dead-reckoned position): the same vertices, segments and
walk as ``Trail``, so the same numbers.
"""

from __future__ import annotations

import math

from openconvoy.envs.vector_jit import kernel

CAPACITY = 1024
"""Breadcrumbs per trail, as ``core.trail.Trail`` (the oldest half dropped when full)."""
FAR_M = 1e4
"""Length of the straight extension behind the oldest breadcrumb (``Trail._vertex``)."""


@kernel
def trail_add(tr, n, b, ln, x, y, spacing):  # pragma: no cover - compiled
    """``Trail.add``: record (x, y) when ``spacing`` m from the last breadcrumb."""
    nn = n[b, ln]
    step = 0.0
    ps = 0.0
    if nn > 0:
        ps = tr[2, b, ln, nn - 1]
        step = math.hypot(x - tr[0, b, ln, nn - 1], y - tr[1, b, ln, nn - 1])
        if step < spacing:
            return
    cap = tr.shape[3]
    if nn >= cap:
        half = cap // 2
        for f in range(3):
            for j in range(cap - half):
                tr[f, b, ln, j] = tr[f, b, ln, j + half]
        nn -= half
    tr[0, b, ln, nn] = x
    tr[1, b, ln, nn] = y
    tr[2, b, ln, nn] = ps + step if nn > 0 else 0.0
    n[b, ln] = nn + 1


@kernel
def _bisect(tr, b, ln, n, value):  # pragma: no cover - compiled
    """``bisect_right`` of ``value`` in the trail's arc coordinates."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if value < tr[2, b, ln, mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@kernel
def _back(tr, b, ln, n, hx, hy, hh):  # pragma: no cover - compiled
    """``Trail._back_direction``: unit vector backwards from the oldest breadcrumb."""
    if n >= 2:
        dx, dy = tr[0, b, ln, 1] - tr[0, b, ln, 0], tr[1, b, ln, 1] - tr[1, b, ln, 0]
    else:
        dx, dy = hx - tr[0, b, ln, 0], hy - tr[1, b, ln, 0]
    d = math.hypot(dx, dy)
    if d < 1e-9:
        return -math.cos(hh), -math.sin(hh)
    return -dx / d, -dy / d


@kernel
def _vertex(tr, b, ln, n, k, hx, hy, hh):  # pragma: no cover - compiled
    """``Trail._vertex``: -1 the far end of the extension, 0..n-1 breadcrumbs, n the head."""
    if k >= n:
        last = n - 1
        return (
            hx,
            hy,
            tr[2, b, ln, last] + math.hypot(hx - tr[0, b, ln, last], hy - tr[1, b, ln, last]),
        )
    if k >= 0:
        return tr[0, b, ln, k], tr[1, b, ln, k], tr[2, b, ln, k]
    bx, by = _back(tr, b, ln, n, hx, hy, hh)
    return tr[0, b, ln, 0] + FAR_M * bx, tr[1, b, ln, 0] + FAR_M * by, tr[2, b, ln, 0] - FAR_M


@kernel
def _segment(tr, b, ln, n, k, hx, hy, hh, x, y):  # pragma: no cover - compiled
    """``Trail._segment``: (dist², s, cross, heading) of (x, y) on segment k -> k+1."""
    ax, ay, sa = _vertex(tr, b, ln, n, k, hx, hy, hh)
    bx, by, sb = _vertex(tr, b, ln, n, k + 1, hx, hy, hh)
    dx, dy = bx - ax, by - ay
    seg = math.hypot(dx, dy)
    rx, ry = x - ax, y - ay
    if seg < 1e-12:
        return rx * rx + ry * ry, sa, 0.0, hh
    u = min(max((rx * dx + ry * dy) / (seg * seg), 0.0), 1.0)
    ex, ey = rx - u * dx, ry - u * dy
    return ex * ex + ey * ey, sa + u * (sb - sa), (dx * ry - dy * rx) / seg, math.atan2(dy, dx)


@kernel
def project(tr, n_arr, b, ln, hx, hy, hh, x, y, expected, hint):  # pragma: no cover - compiled
    """``Trail.project`` from ``hint`` (NaN: ``expected`` m behind the head):
    (arc to head, cross track, path heading, s)."""
    n = n_arr[b, ln]
    lx, ly = tr[0, b, ln, n - 1], tr[1, b, ln, n - 1]
    last = n - 1 if math.hypot(hx - lx, hy - ly) > 1e-9 else n - 2
    s_head = tr[2, b, ln, n - 1] + math.hypot(hx - lx, hy - ly)
    start = s_head - expected if math.isnan(hint) else hint
    k = min(max(_bisect(tr, b, ln, n, start) - 1, -1), last)
    d2, s, cross, heading = _segment(tr, b, ln, n, k, hx, hy, hh, x, y)
    for step in (1, -1):
        j = k + step
        while -1 <= j <= last:
            c2, cs, cc, ch = _segment(tr, b, ln, n, j, hx, hy, hh, x, y)
            if c2 >= d2:
                break
            d2, s, cross, heading = c2, cs, cc, ch
            k = j
            j += step
    return s_head - s, cross, heading, s


@kernel
def point_at(tr, n_arr, b, ln, hx, hy, hh, s):  # pragma: no cover - compiled
    """``Trail.point_at``: the path point at arc coordinate ``s`` (beyond the head: on)."""
    n = n_arr[b, ln]
    lx, ly, ls = tr[0, b, ln, n - 1], tr[1, b, ln, n - 1], tr[2, b, ln, n - 1]
    s_head = ls + math.hypot(hx - lx, hy - ly)
    if s >= s_head and not s_head - ls > 1e-9:
        return hx + (s - s_head) * math.cos(hh), hy + (s - s_head) * math.sin(hh)
    if s >= ls:
        f = (s - ls) / (s_head - ls)
        return lx + f * (hx - lx), ly + f * (hy - ly)
    s0 = tr[2, b, ln, 0]
    if s <= s0:
        bx, by = _back(tr, b, ln, n, hx, hy, hh)
        return tr[0, b, ln, 0] - (s - s0) * bx, tr[1, b, ln, 0] - (s - s0) * by
    i = min(max(_bisect(tr, b, ln, n, s) - 1, 0), max(n - 2, 0))
    xi, yi, si = tr[0, b, ln, i], tr[1, b, ln, i], tr[2, b, ln, i]
    f = (s - si) / (tr[2, b, ln, i + 1] - si)
    return xi + f * (tr[0, b, ln, i + 1] - xi), yi + f * (tr[1, b, ln, i + 1] - yi)
