"""A cheap picture of the convoy: numpy rasterization, no plotting library.

Vehicles are drawn as oriented rectangles (at least a few pixels, so small cars on a long
road stay visible), coloured by mode; the road is a grey line. The view fits the convoy
with a margin, north up.
"""

from __future__ import annotations

import math

import numpy as np

MODE_COLOURS: dict[str, tuple[int, int, int]] = {
    "leader": (30, 90, 200),
    "coop": (40, 160, 60),
    "degraded": (230, 160, 20),
    "stop": (210, 40, 40),
    "failsafe": (120, 0, 120),
}
BACKGROUND = (245, 245, 240)
ROAD = (170, 170, 170)


def draw_convoy(
    x: np.ndarray,
    y: np.ndarray,
    heading: np.ndarray,
    lengths: np.ndarray,
    widths: np.ndarray,
    modes: list[str],
    road: np.ndarray | None = None,
    size: tuple[int, int] = (300, 600),
    margin_m: float = 5.0,
    min_px: float = 4.0,
) -> np.ndarray:
    """An RGB image (H x W x 3, uint8) of the vehicles; ``modes[i]`` picks the colour."""
    h_px, w_px = size
    img = np.empty((h_px, w_px, 3), dtype=np.uint8)
    img[:] = BACKGROUND
    x0, x1 = float(np.min(x)) - margin_m, float(np.max(x)) + margin_m
    y0, y1 = float(np.min(y)) - margin_m, float(np.max(y)) + margin_m
    scale = min(w_px / (x1 - x0), h_px / (y1 - y0))  # pixels per metre
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2

    def to_px(px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (px - cx) * scale + w_px / 2, h_px / 2 - (py - cy) * scale

    if road is not None and len(road):
        u, v = to_px(road[:, 0], road[:, 1])
        ok = (u >= 0) & (u < w_px) & (v >= 0) & (v < h_px)
        img[v[ok].astype(int), u[ok].astype(int)] = ROAD
        # A straight road sampled at its two ends: draw the line between them too.
        if len(road) == 2:
            t = np.linspace(0.0, 1.0, 4 * (w_px + h_px))
            u = u[0] + (u[1] - u[0]) * t
            v = v[0] + (v[1] - v[0]) * t
            ok = (u >= 0) & (u < w_px) & (v >= 0) & (v < h_px)
            img[v[ok].astype(int), u[ok].astype(int)] = ROAD
    for i in range(len(x)):
        half_l = max(lengths[i] * scale, min_px) / 2
        half_w = max(widths[i] * scale, min_px * 0.6) / 2
        u, v = to_px(np.array(x[i]), np.array(y[i]))
        c, s = math.cos(heading[i]), math.sin(heading[i])
        r = int(math.ceil(math.hypot(half_l, half_w))) + 1
        ui, vi = int(u), int(v)
        ua, ub = max(ui - r, 0), min(ui + r + 1, w_px)
        va, vb = max(vi - r, 0), min(vi + r + 1, h_px)
        if ua >= ub or va >= vb:
            continue
        gu, gv = np.meshgrid(np.arange(ua, ub) + 0.5 - u, np.arange(va, vb) + 0.5 - v)
        # Image v grows downwards: flip it to get the ENU-aligned offset.
        along = gu * c - gv * s
        across = gu * s + gv * c
        mask = (np.abs(along) <= half_l) & (np.abs(across) <= half_w)
        img[va:vb, ua:ub][mask] = MODE_COLOURS.get(modes[i], (0, 0, 0))
    return img
