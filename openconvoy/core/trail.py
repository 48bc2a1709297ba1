"""A vehicle's trail: the breadcrumb path it drove, for path-based following.

Followers follow their predecessors' trails (DESIGN.md): the point at the desired following
distance is measured along the predecessor's path, and the ego's gap is the arc length from
its projection on that path to the predecessor. Positions are ENU metres.

The path a query sees is: a straight extension behind the oldest breadcrumb (a vehicle
that has not moved yet is assumed to have come straight along its heading), the
breadcrumbs, and the vehicle's present (dead-reckoned) position, the *head*. Arc lengths
``s`` are measured from the first breadcrumb ever recorded and stay valid when old
breadcrumbs are dropped (smaller than the oldest kept one on the extension). Queries are
plain Python on a few segments: they run every control tick for every target.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

SMOOTHING = 0.25
"""Weight of a new position fix against the track predicted from the sender's own speed
and heading (``Trail.add``): GPS noise of σ leaves ~0.38σ on the breadcrumbs, and no lag
at a steady speed (the prediction carries the motion)."""


@dataclass(frozen=True, slots=True)
class Projection:
    """Where a point projects on a trail.

    ``arc_to_head``: arc length from the projection to the head (m); ``cross_track``:
    signed offset of the point from the path (m, positive = point left of the path);
    ``heading``: the path's heading there (rad); ``s``: arc coordinate of the projection.
    """

    arc_to_head: float
    cross_track: float
    heading: float
    s: float


class Trail:
    """Breadcrumbs at least ``spacing_m`` apart, newest last, at most ``capacity`` of them
    (the oldest half is dropped when full).

    Robust to positioning noise (issue 22, the PX4 start stall): with the sender's
    heading, speed and time, the positions are smoothed along the motion they report
    (``SMOOTHING``), a breadcrumb is laid only for ``spacing_m`` of progress along that
    heading (a fix that jitters or creeps at rest lays none), and the extension behind
    the oldest breadcrumb follows the heading the sender reported there, not a
    direction taken from two close, noisy points."""

    # A member keeps a trail per vehicle it hears: a long all-predecessors convoy holds
    # N²/2 of them, so no per-instance dict.
    __slots__ = ("spacing_m", "capacity", "_x", "_y", "_s", "_back", "_fix")

    def __init__(self, spacing_m: float = 0.2, capacity: int = 1024) -> None:
        self.spacing_m = spacing_m
        self.capacity = capacity
        self.clear()

    def __len__(self) -> int:
        return len(self._x)

    def clear(self) -> None:
        self._x: list[float] = []
        self._y: list[float] = []
        self._s: list[float] = []
        self._back: tuple[float, float] | None = None  # unit vector behind the oldest
        self._fix: tuple[float, float, float] | None = None  # smoothed x, y (m), t (s)

    def add(
        self,
        x: float,
        y: float,
        heading: float | None = None,
        speed: float = 0.0,
        t: float = 0.0,
    ) -> None:
        """Record a position (m) sent at ``t`` (s) by a vehicle reporting ``heading``
        (rad) and ``speed`` (m/s): smoothed, and laid as a breadcrumb after ``spacing_m``
        of progress along ``heading``. Without a heading: the raw position, laid when
        ``spacing_m`` from the last breadcrumb."""
        if heading is not None:
            c, s = math.cos(heading), math.sin(heading)
            fix = self._fix
            if fix is not None:
                d = speed * (t - fix[2])
                px, py = fix[0] + d * c, fix[1] + d * s
                x, y = px + SMOOTHING * (x - px), py + SMOOTHING * (y - py)
            self._fix = (x, y, t)
            if self._x and (x - self._x[-1]) * c + (y - self._y[-1]) * s < self.spacing_m:
                return
            if not self._x:
                self._back = (-c, -s)
        step = math.hypot(x - self._x[-1], y - self._y[-1]) if self._x else 0.0
        if self._x and step < self.spacing_m:
            return
        if len(self._x) >= self.capacity:
            half = self.capacity // 2
            # Arc coordinates stay absolute, so a caller's remembered ``s`` stays valid.
            del self._x[:half], self._y[:half], self._s[:half]
            self._back = None
        self._x.append(x)
        self._y.append(y)
        self._s.append(self._s[-1] + step if self._s else 0.0)

    # --- queries ---------------------------------------------------------------------

    def _vertex(
        self, k: int, head: tuple[float, float], heading: float
    ) -> tuple[float, float, float]:
        """Vertex ``k`` of the query path: -1 = far end of the extension, 0..n-1 the
        breadcrumbs, n the head. Returns ``(x, y, s)``."""
        n = len(self._x)
        if 0 <= k < n:
            return self._x[k], self._y[k], self._s[k]
        if k >= n:
            return (
                head[0],
                head[1],
                self._s[-1] + math.hypot(head[0] - self._x[-1], head[1] - self._y[-1]),
            )
        if k >= 0:
            return self._x[k], self._y[k], self._s[k]
        hx, hy = self._back_direction(head, heading)
        far = 1e4
        return self._x[0] + far * hx, self._y[0] + far * hy, self._s[0] - far

    def _back_direction(self, head: tuple[float, float], heading: float) -> tuple[float, float]:
        """Unit vector pointing backwards from the oldest breadcrumb: against the heading
        reported there, else from the two oldest breadcrumbs."""
        if self._back is not None:
            return self._back
        if len(self._x) >= 2:
            dx, dy = self._x[1] - self._x[0], self._y[1] - self._y[0]
        else:
            dx, dy = head[0] - self._x[0], head[1] - self._y[0]
        d = math.hypot(dx, dy)
        if d < 1e-9:
            return -math.cos(heading), -math.sin(heading)
        return -dx / d, -dy / d

    def _segment(
        self, k: int, head: tuple[float, float], heading: float, x: float, y: float
    ) -> tuple[float, float, float, float, float]:
        """Project (x, y) on segment k (vertex k → k+1): ``(dist², s, cross, heading, len)``."""
        ax, ay, sa = self._vertex(k, head, heading)
        bx, by, sb = self._vertex(k + 1, head, heading)
        return _segment(ax, ay, sa, bx, by, sb, heading, x, y)

    def head_s(self, head: tuple[float, float]) -> float:
        """Arc coordinate (m) of the head: the newest breadcrumb's, plus the straight
        distance from it to ``head``."""
        return self._s[-1] + math.hypot(head[0] - self._x[-1], head[1] - self._y[-1])

    def project(
        self,
        head: tuple[float, float],
        heading: float,
        x: float,
        y: float,
        expected_arc: float,
        hint_s: float | None = None,
    ) -> Projection:
        """Project ``(x, y)`` on the path ending at ``head``. The search starts at arc
        coordinate ``hint_s`` (the last projection's ``s``) or, without one, where the
        point is expected (``expected_arc`` metres behind the head), and walks to the
        nearest segment: a few segments per tick for a vehicle moving along the path."""
        xs, ys, ss = self._x, self._y, self._s
        if not xs:
            raise ValueError("cannot project on an empty trail")
        n = len(xs)
        hx, hy = head
        last = n - 1 if math.hypot(hx - xs[-1], hy - ys[-1]) > 1e-9 else n - 2
        s_head = self.head_s(head)
        back: tuple[float, float, float] | None = None

        def vertex(k: int) -> tuple[float, float, float]:
            # ``_vertex``, with the head's and the extension's vertices computed once.
            nonlocal back
            if 0 <= k < n:
                return xs[k], ys[k], ss[k]
            if k >= n:
                return hx, hy, s_head
            if back is None:
                back = self._vertex(-1, head, heading)
            return back

        def dist2(k: int) -> float:
            ax, ay, _ = vertex(k)
            bx, by, _ = vertex(k + 1)
            return _segment_dist2(ax, ay, bx, by, x, y)

        start = hint_s if hint_s is not None else s_head - expected_arc
        k = min(max(bisect_right(ss, start) - 1, -1), last)
        best_d2 = dist2(k)
        for step in (1, -1):
            j = k + step
            while -1 <= j <= last:
                d2 = dist2(j)
                if d2 >= best_d2:
                    break
                best_d2, k = d2, j
                j += step
        ax, ay, sa = vertex(k)
        bx, by, sb = vertex(k + 1)
        _, s_proj, cross, path_heading, _ = _segment(ax, ay, sa, bx, by, sb, heading, x, y)
        return Projection(
            arc_to_head=s_head - s_proj, cross_track=cross, heading=path_heading, s=s_proj
        )

    def point_at(
        self,
        head: tuple[float, float],
        heading: float,
        s: float,
        s_head: float | None = None,
    ) -> tuple[float, float]:
        """The path point at arc coordinate ``s`` (beyond the head: straight on);
        ``s_head`` is ``head_s(head)`` when the caller has it."""
        if s_head is None:
            s_head = self.head_s(head)
        xs, ys, ss = self._x, self._y, self._s
        if s >= s_head:
            if s_head - ss[-1] > 1e-9:
                ax, ay = xs[-1], ys[-1]
                f = (s - ss[-1]) / (s_head - ss[-1])
                return ax + f * (head[0] - ax), ay + f * (head[1] - ay)
            return head[0] + (s - s_head) * math.cos(heading), head[1] + (s - s_head) * math.sin(
                heading
            )
        if s >= ss[-1]:
            f = (s - ss[-1]) / (s_head - ss[-1])
            return xs[-1] + f * (head[0] - xs[-1]), ys[-1] + f * (head[1] - ys[-1])
        if s <= ss[0]:
            bx, by = self._back_direction(head, heading)
            return xs[0] - (s - ss[0]) * bx, ys[0] - (s - ss[0]) * by
        i = bisect_right(ss, s) - 1
        f = (s - ss[i]) / (ss[i + 1] - ss[i])
        return xs[i] + f * (xs[i + 1] - xs[i]), ys[i] + f * (ys[i + 1] - ys[i])


def _segment_dist2(ax: float, ay: float, bx: float, by: float, x: float, y: float) -> float:
    """``_segment``'s squared distance alone (the walk compares only that)."""
    dx, dy = bx - ax, by - ay
    seg = math.hypot(dx, dy)
    if seg < 1e-12:
        return (x - ax) ** 2 + (y - ay) ** 2
    rx, ry = x - ax, y - ay
    u = min(max((rx * dx + ry * dy) / (seg * seg), 0.0), 1.0)
    ex, ey = rx - u * dx, ry - u * dy
    return ex * ex + ey * ey


def _segment(
    ax: float,
    ay: float,
    sa: float,
    bx: float,
    by: float,
    sb: float,
    heading: float,
    x: float,
    y: float,
) -> tuple[float, float, float, float, float]:
    """Project (x, y) on the segment a → b: ``(dist², s, cross, heading, len)``."""
    dx, dy = bx - ax, by - ay
    seg = math.hypot(dx, dy)
    if seg < 1e-12:
        return (x - ax) ** 2 + (y - ay) ** 2, sa, 0.0, heading, 0.0
    rx, ry = x - ax, y - ay
    u = min(max((rx * dx + ry * dy) / (seg * seg), 0.0), 1.0)
    ex, ey = rx - u * dx, ry - u * dy
    return (
        ex * ex + ey * ey,
        sa + u * (sb - sa),
        (dx * ry - dy * rx) / seg,
        math.atan2(dy, dx),
        seg,
    )
