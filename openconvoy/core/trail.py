"""A vehicle's trail: the breadcrumb path it drove, for path-based following.

Followers follow their predecessors' trails (DESIGN.md): the point at the desired following
distance is measured along the predecessor's path, and the ego's gap is the arc length from
its projection on that path to the predecessor. Positions are ENU metres.
"""

from __future__ import annotations

import math

import numpy as np


class Trail:
    """A bounded polyline of positions, newest last, with breadcrumbs ``spacing_m`` apart.

    ``capacity`` bounds memory; the oldest breadcrumbs fall off. When the path is shorter
    than asked for, it is extended backwards along its oldest heading (a vehicle that has
    not moved yet is assumed to have come straight along its current heading).
    """

    def __init__(self, spacing_m: float = 0.2, capacity: int = 1024) -> None:
        self.spacing_m = spacing_m
        self.capacity = capacity
        self._xy = np.zeros((capacity, 2))
        self._cum = np.zeros(capacity)  # arc length from the oldest breadcrumb, m
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def clear(self) -> None:
        self._n = 0

    def add(self, x: float, y: float, heading: float) -> None:
        """Record a position; kept only when ``spacing_m`` from the last breadcrumb."""
        n = self._n
        step = 0.0
        if n:
            lx, ly = self._xy[n - 1]
            step = math.hypot(x - lx, y - ly)
            if step < self.spacing_m:
                return
        if n == self.capacity:
            # Drop the oldest half at once: amortized O(1) per add.
            keep = self.capacity // 2
            self._xy[:keep] = self._xy[n - keep : n]
            self._cum[:keep] = self._cum[n - keep : n] - self._cum[n - keep]
            n = self._n = keep
        self._xy[n] = (x, y)
        self._cum[n] = self._cum[n - 1] + step if n else 0.0
        self._n = n + 1

    def polyline(self, head: tuple[float, float], heading: float, back_m: float) -> np.ndarray:
        """Points from about ``back_m`` behind ``head`` (the vehicle's present position) to
        ``head``, oldest first, extended backwards when the trail is shorter. Shape (n, 2)."""
        n = self._n
        hx, hy = head
        if n == 0:
            pts, length = np.array([[hx, hy]]), 0.0
        else:
            # Only the part of the trail within back_m of its newest breadcrumb matters.
            cum = self._cum[:n]
            i0 = max(int(np.searchsorted(cum, cum[-1] - back_m, side="right")) - 1, 0)
            pts, length = self._xy[i0:n], float(cum[-1] - cum[i0])
            tail = math.hypot(hx - pts[-1, 0], hy - pts[-1, 1])
            if tail > 1e-9:
                pts, length = np.concatenate([pts, ((hx, hy),)]), length + tail
        d0 = pts[1] - pts[0] if len(pts) >= 2 else None
        if length < back_m:
            if d0 is not None and abs(d0[0]) + abs(d0[1]) > 1e-9:
                h0 = math.atan2(d0[1], d0[0])
            else:
                h0 = heading
            extra = back_m - length + 1.0
            start = (pts[0, 0] - extra * math.cos(h0), pts[0, 1] - extra * math.sin(h0))
            pts = np.concatenate([(start,), pts])
        return pts


def project(pts: np.ndarray, x: float, y: float) -> tuple[float, float, float]:
    """Project ``(x, y)`` on the polyline ``pts`` (oldest → newest, at least 2 points).

    Returns ``(arc_to_head_m, cross_track_m, path_heading_rad)``: arc length from the
    projection to the newest point, signed lateral offset (positive = point left of the
    path), and the path's heading at the projection.
    """
    ax, ay = pts[:-1, 0], pts[:-1, 1]
    dx, dy = pts[1:, 0] - ax, pts[1:, 1] - ay
    seg_len2 = np.maximum(dx * dx + dy * dy, 1e-12)
    rx, ry = x - ax, y - ay
    s = np.clip((rx * dx + ry * dy) / seg_len2, 0.0, 1.0)
    ex, ey = rx - dx * s, ry - dy * s
    i = int(np.argmin(ex * ex + ey * ey))
    seg_len = np.sqrt(seg_len2)
    arc_to_head = float(seg_len[i] * (1.0 - s[i]) + seg_len[i + 1 :].sum())
    heading = math.atan2(dy[i], dx[i])
    cross = float(dx[i] * ry[i] - dy[i] * rx[i]) / float(seg_len[i])
    return arc_to_head, cross, heading


def points_at(pts: np.ndarray, arcs_from_head: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``arcs_from_head`` metres back along the polyline from its newest point
    (negative: beyond the head, extrapolated along the last segment). Returns ``(xs, ys)``."""
    d = np.diff(pts, axis=0)
    seg = np.hypot(d[:, 0], d[:, 1])
    cum = np.concatenate(([0.0], np.cumsum(seg)))
    s = cum[-1] - np.asarray(arcs_from_head, dtype=float)
    xs = np.interp(s, cum, pts[:, 0])
    ys = np.interp(s, cum, pts[:, 1])
    beyond = s > cum[-1]
    if beyond.any():
        h = math.atan2(d[-1, 1], d[-1, 0]) if len(seg) else 0.0
        ex = s[beyond] - cum[-1]
        xs[beyond] = pts[-1, 0] + ex * math.cos(h)
        ys[beyond] = pts[-1, 1] + ex * math.sin(h)
    return xs, ys


def point_at_arc(pts: np.ndarray, arc_from_head: float) -> tuple[float, float]:
    """One point of ``points_at``: ``(x, y)``."""
    xs, ys = points_at(pts, np.array([arc_from_head]))
    return float(xs[0]), float(ys[0])
