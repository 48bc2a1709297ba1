"""A driving path: a polyline in the local ENU frame, parametrized by arc length.

Scenarios describe the road (or lab track) as a path; the leader's driver follows it and
vehicles are placed on it. Open paths end; closed paths wrap around (arc length modulo the
perimeter).
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from openconvoy.core.errors import ConfigError


class Path:
    """A polyline through ``points`` (N x 2, metres, ENU), optionally closed.

    Attributes:
        points: vertices, metres (a closed path does not repeat the first vertex).
        closed: whether the last vertex connects back to the first.
        length: total arc length, metres (the perimeter when closed).
    """

    def __init__(self, points: np.ndarray, closed: bool = False) -> None:
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
            raise ConfigError("a path needs at least two (x, y) points")
        if closed and np.hypot(*(pts[-1] - pts[0])) < 1e-9:
            pts = pts[:-1]
        # Drop repeated vertices: zero-length segments have no heading.
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.hypot(*np.diff(pts, axis=0).T) > 1e-9
        pts = pts[keep]
        if len(pts) < 2:
            raise ConfigError("a path needs at least two distinct (x, y) points")
        self.points = pts
        self.closed = closed
        verts = np.vstack([pts, pts[:1]]) if closed else pts
        seg = np.diff(verts, axis=0)
        self._seg_len = np.hypot(seg[:, 0], seg[:, 1])
        self._seg_dir = seg / self._seg_len[:, None]
        self._seg_heading = np.arctan2(seg[:, 1], seg[:, 0])
        self._s = np.concatenate([[0.0], np.cumsum(self._seg_len)])
        self._a = verts[:-1]
        self.length = float(self._s[-1])
        # Python lists for the scalar fast path (numpy scalar indexing is slow per step).
        self._a_list = self._a.tolist()
        self._heading_list = self._seg_heading.tolist()
        self._dir_list = self._seg_dir.tolist()
        self._s_list = self._s.tolist()

    def _wrap(self, s: float) -> float:
        if self.closed:
            return s % self.length
        return min(max(s, 0.0), self.length)

    def _segment(self, s: float) -> int:
        i = bisect.bisect_right(self._s_list, s) - 1
        return min(max(i, 0), len(self._seg_len) - 1)

    def point_at(self, s: float) -> tuple[float, float]:
        """The point at arc length ``s`` (m); open paths extend along their end segments."""
        if self.closed:
            s = s % self.length
        i = self._segment(s)
        ax, ay = self._a_list[i]
        dx, dy = self._dir_list[i]
        u = s - self._s_list[i]
        return ax + dx * u, ay + dy * u

    def heading_at(self, s: float) -> float:
        """The path's direction at arc length ``s``, radians (ENU, CCW from east)."""
        return self._heading_list[self._segment(self._wrap(s))]

    def project(
        self, x: float, y: float, s_hint: float | None = None, window_m: float = 20.0
    ) -> float:
        """Arc length of the path point nearest to (x, y), metres.

        With ``s_hint`` only segments within ``window_m`` of it are searched (the leader
        moves a little per tick; a local search also keeps a closed loop from snapping to
        the opposite straight).
        """
        n = len(self._seg_len)
        if n == 1:
            # A straight road: scalar arithmetic (this runs every tick for the leader).
            ax, ay = self._a_list[0]
            dx, dy = self._dir_list[0]
            u = min(max((x - ax) * dx + (y - ay) * dy, 0.0), self.length)
            return u
        if s_hint is None or n <= 2:
            idx = np.arange(n)
        else:
            lo = s_hint - window_m
            hi = s_hint + window_m
            if self.closed:
                i0 = self._segment(lo % self.length)
                i1 = self._segment(hi % self.length)
                span = (i1 - i0) % n + 1
                idx = (i0 + np.arange(min(span, n))) % n
            else:
                i0 = self._segment(max(lo, 0.0))
                i1 = self._segment(min(hi, self.length))
                idx = np.arange(i0, i1 + 1)
        a = self._a[idx]
        d = self._seg_dir[idx]
        u = np.clip((x - a[:, 0]) * d[:, 0] + (y - a[:, 1]) * d[:, 1], 0.0, self._seg_len[idx])
        px = a[:, 0] + d[:, 0] * u
        py = a[:, 1] + d[:, 1] * u
        k = int(np.argmin((px - x) ** 2 + (py - y) ** 2))
        s = float(self._s[idx[k]] + u[k])
        return s % self.length if self.closed else s

    def advance(self, s: float, ds: float) -> float:
        """Arc length ``ds`` metres further along from ``s`` (wrapping when closed)."""
        return (s + ds) % self.length if self.closed else s + ds

    def sample(self, spacing_m: float = 0.5) -> np.ndarray:
        """Points every ``spacing_m`` metres along the path (N x 2), e.g. for drawing."""
        count = max(2, int(math.ceil(self.length / spacing_m)) + 1)
        s = np.linspace(0.0, self.length, count)
        return np.array([self.point_at(v) for v in s])


def straight_road(x_start: float, x_end: float, heading: float = 0.0) -> Path:
    """A straight road through the origin along ``heading``, from ``x_start`` to ``x_end`` m."""
    c, s = math.cos(heading), math.sin(heading)
    return Path(np.array([[x_start * c, x_start * s], [x_end * c, x_end * s]]))


def oval(straight_m: float, radius_m: float, step_m: float = 0.25) -> Path:
    """A closed oval: two straights of ``straight_m`` joined by semicircles of ``radius_m``.

    Driven counter-clockwise, starting at the beginning of the bottom straight, which runs
    east from (-straight_m/2, -radius_m).
    """
    if straight_m < 0 or radius_m <= 0:
        raise ConfigError("oval needs straight_m >= 0 and radius_m > 0")
    half = straight_m / 2.0
    k = max(8, int(math.ceil(math.pi * radius_m / step_m)))
    pts = [(-half, -radius_m), (half, -radius_m)]
    ang = np.linspace(-math.pi / 2, math.pi / 2, k + 1)[1:]
    pts += [(half + radius_m * math.cos(a), radius_m * math.sin(a)) for a in ang]
    pts.append((-half, radius_m))
    ang = np.linspace(math.pi / 2, 3 * math.pi / 2, k + 1)[1:-1]
    pts += [(-half + radius_m * math.cos(a), radius_m * math.sin(a)) for a in ang]
    return Path(np.array(pts), closed=True)
