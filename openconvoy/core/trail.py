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

    def __init__(self, spacing_m: float = 0.2, capacity: int = 512) -> None:
        self.spacing_m = spacing_m
        self.capacity = capacity
        self._xy = np.zeros((capacity, 2))
        self._n = 0
        self._heading = 0.0  # heading of the newest sample, rad

    def __len__(self) -> int:
        return self._n

    def clear(self) -> None:
        self._n = 0

    def add(self, x: float, y: float, heading: float) -> None:
        """Record a position; kept only when ``spacing_m`` from the last breadcrumb."""
        self._heading = heading
        if self._n:
            lx, ly = self._xy[self._n - 1]
            if math.hypot(x - lx, y - ly) < self.spacing_m:
                return
        if self._n == self.capacity:
            # Drop the oldest half at once: amortized O(1) per add.
            keep = self.capacity // 2
            self._xy[:keep] = self._xy[self._n - keep : self._n]
            self._n = keep
        self._xy[self._n] = (x, y)
        self._n += 1

    def polyline(self, head: tuple[float, float], heading: float, back_m: float) -> np.ndarray:
        """Points from the oldest to ``head`` (the vehicle's present position), extended
        backwards so the polyline is at least ``back_m`` long. Shape (n, 2)."""
        pts = self._xy[: self._n]
        hx, hy = head
        if self._n == 0 or math.hypot(pts[-1, 0] - hx, pts[-1, 1] - hy) > 1e-9:
            pts = np.vstack([pts, (hx, hy)]) if self._n else np.array([[hx, hy]])
        seg = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
        length = float(seg.sum())
        if length < back_m:
            if len(pts) >= 2:
                d = pts[1] - pts[0]
                h0 = math.atan2(d[1], d[0]) if np.hypot(*d) > 1e-9 else heading
            else:
                h0 = heading
            extra = back_m - length + 1.0
            start = pts[0] - extra * np.array([math.cos(h0), math.sin(h0)])
            pts = np.vstack([start, pts])
        return pts


def project(pts: np.ndarray, x: float, y: float) -> tuple[float, float, float]:
    """Project ``(x, y)`` on the polyline ``pts`` (oldest → newest).

    Returns ``(arc_to_head_m, cross_track_m, path_heading_rad)``: arc length from the
    projection to the newest point, signed lateral offset (positive = point left of the
    path), and the path's heading at the projection.
    """
    a = pts[:-1]
    d = pts[1:] - a
    seg_len2 = np.maximum((d * d).sum(axis=1), 1e-12)
    rel = np.array([x, y]) - a
    s = np.clip((rel * d).sum(axis=1) / seg_len2, 0.0, 1.0)
    proj = a + d * s[:, None]
    dist2 = ((np.array([x, y]) - proj) ** 2).sum(axis=1)
    i = int(np.argmin(dist2))
    seg_len = np.sqrt(seg_len2)
    arc_to_head = float(seg_len[i] * (1.0 - s[i]) + seg_len[i + 1 :].sum())
    heading = math.atan2(d[i, 1], d[i, 0])
    cross = float(d[i, 0] * rel[i, 1] - d[i, 1] * rel[i, 0]) / float(seg_len[i])
    return arc_to_head, cross, heading


def point_at_arc(pts: np.ndarray, arc_from_head: float) -> tuple[float, float, float]:
    """The point ``arc_from_head`` metres back along the polyline from its newest point
    (negative: beyond the head, extrapolated). Returns ``(x, y, path_heading_rad)``."""
    d = np.diff(pts, axis=0)
    seg = np.hypot(d[:, 0], d[:, 1])
    if arc_from_head <= 0.0 or len(seg) == 0:
        h = math.atan2(d[-1, 1], d[-1, 0]) if len(seg) else 0.0
        ex = -arc_from_head
        return float(pts[-1, 0] + ex * math.cos(h)), float(pts[-1, 1] + ex * math.sin(h)), h
    back = np.cumsum(seg[::-1])  # arc from head to each older vertex
    j = int(np.searchsorted(back, arc_from_head))
    if j >= len(seg):
        j = len(seg) - 1
    i = len(seg) - 1 - j  # segment index (pts[i] -> pts[i+1])
    before = back[j - 1] if j > 0 else 0.0
    frac = 1.0 - (arc_from_head - before) / max(seg[i], 1e-12)
    frac = min(max(frac, 0.0), 1.0)
    p = pts[i] + d[i] * frac
    return float(p[0]), float(p[1]), math.atan2(d[i, 1], d[i, 0])
