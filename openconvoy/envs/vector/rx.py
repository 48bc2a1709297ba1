"""The receivers' side of the batched simulator: R^i buffers and trails per kept link.

Per kept link ``ln`` (receiver, sender) of convoy ``b``: ``hist[b, ln]`` (k, 6) the last
``k`` states, newest first (t s, x m, y m, speed m/s, heading rad, accel m/s², and the
heading's cosine and sine: one cache line a state, no trigonometry per reader),
``hist_n`` how many, ``newest[b, ln]`` the newest one's time (-inf: none). Only what the receiver reads is kept (``LinkTables``): the states of
the links in its observation slots and targets, of the others only the newest time (the
ladder's age; the same ages, so the same run). Per target link, row ``trail_of[ln]`` of
the trails: the sender's trail (``vector.trail``); ``hint`` the last projection's arc
coordinate on it (NaN: none) and ``hint_k`` its segment (where the next search starts).
A link's data is contiguous: a push touches a few cache lines. ``StateBuffer.push`` +
``Trail.add``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from openconvoy.envs.vector.jit import bare_inline, bare_kernel
from openconvoy.envs.vector.links import LinkTables
from openconvoy.envs.vector.plant import cos_sin
from openconvoy.envs.vector.trail import T_BASE, T_REACH, TAIL, trail_add

T, HX, HY, HV, HH, HA, HC, HS = range(8)
"""Fields of ``hist``'s last axis."""
FIELDS = 8


def aligned_zeros(shape: tuple[int, ...]) -> np.ndarray:
    """Zeros (float64) starting on a cache line (64 bytes): a state (8 doubles) or two
    breadcrumbs (4 each) then fill one line, not two."""
    n = int(np.prod(shape))
    raw = np.zeros(n + 8)
    start = (-raw.ctypes.data % 64) // 8
    return raw[start : start + n].reshape(shape)


WIDEN_SLICES = 16
"""Slices of convoys ``RxBuffers.widen`` moves one after another: the old rings' memory
shrinks by one slice as the new ones' grows by one."""


class Pushed(NamedTuple):
    """What ``push_one`` writes and reads (``RxBuffers.pushed``, built again when the
    trails' rings widen): the R^i buffers ``hist``, ``hist_n``, ``newest``, the trails
    ``trail``, ``tail``, ``trail_n``; per link whether it ``keeps`` states and its trail
    row ``trail_of`` (-1: none); the breadcrumbs' ``spacing`` (m)."""

    hist: np.ndarray
    hist_n: np.ndarray
    newest: np.ndarray
    keeps: np.ndarray
    trail: np.ndarray
    tail: np.ndarray
    trail_n: np.ndarray
    trail_of: np.ndarray
    spacing: float


class RxBuffers:
    """R^i buffers of ``links.L`` kept links, trails and projection hints of ``links.T``
    target links, in ``B`` convoys."""

    def __init__(self, B: int, links: LinkTables, k: int, spacing_m: float, window: int) -> None:
        self.k, self.spacing_m = k, spacing_m
        self.keeps_states, self.trail_of = links.keeps_states, links.trail_of
        L, T = max(links.L, 1), max(links.T, 1)  # placeholders keep "no link" reads in bounds
        self.hist = aligned_zeros((B, L, k, FIELDS))
        # Counts in small exact integers (at most k <= 100 states, CAPACITY breadcrumbs).
        self.hist_n = np.zeros((B, L), dtype=np.int16)
        self.newest = np.full((B, L), -np.inf)
        # Each trail's newest ``window`` breadcrumbs in a ring (``vector.trail``).
        self.trail = np.zeros((B, T, window, 3))
        self.tail = aligned_zeros((B, T, TAIL))
        self.trail_n = np.zeros((B, T), dtype=np.int16)
        self.hint = np.full((B, T), np.nan)
        self.hint_k = np.zeros((B, T), dtype=np.int16)
        self.pushed = self._pushed()

    def _pushed(self) -> Pushed:
        """``push_one``'s arrays of those held now."""
        return Pushed(self.hist, self.hist_n, self.newest, self.keeps_states, self.trail,
                      self.tail, self.trail_n, self.trail_of, float(self.spacing_m))  # fmt: skip

    def reset(self, rows: np.ndarray) -> None:
        """Empty the buffers of convoys ``rows`` (bool (B,))."""
        self.hist_n[rows] = 0
        self.newest[rows] = -np.inf
        self.trail_n[rows] = 0
        self.tail[rows] = 0.0
        self.hint[rows] = np.nan
        self.hint_k[rows] = 0

    @property
    def window(self) -> int:
        """Breadcrumbs each trail's ring holds."""
        return int(self.trail.shape[2])

    def reach(self) -> float:
        """The most breadcrumbs back from a trail's newest that a read went (``trail``)."""
        return float(self.tail[..., T_REACH].max())

    def widen(self, window: int) -> None:
        """Rings of ``window`` breadcrumbs (a wider power of two), the same contents: a
        breadcrumb's place is its count since the reset modulo the ring size. The old
        rings are moved a slice of convoys at a time from the end, the array shrunk
        behind each (``realloc`` hands a large one's pages back), so the two are not
        held whole at once: at B = 16,384 they were a run's peak memory. The new array
        is numpy's own (zero pages until written, huge pages where numpy asks for them);
        every other holder of the old one (the env's packed stages) is built again by the
        caller before the next tick."""
        old = self.trail
        B, T, w, _ = old.shape
        new = np.zeros((B, T, window, 3))
        step = max(1, -(-B // WIDEN_SLICES))
        for b1 in range(B, 0, -step):
            b0 = max(b1 - step, 0)
            _rering(old[b0:b1], self.tail[b0:b1], self.trail_n[b0:b1], new[b0:b1])
            if b0 > 0:
                old.resize((b0, T, w, 3), refcheck=False)
        self.trail = new
        self.pushed = self._pushed()


@bare_kernel
def _rering(old, tail, n, new):  # pragma: no cover - compiled
    """Each trail's breadcrumbs of ring ``old`` into ring ``new`` (both powers of two):
    breadcrumb count ``c`` since the reset sits in slot ``c mod`` the ring's size. A loop,
    not fancy indexing: no temporaries the size of the rings at a large batch."""
    w, wn = old.shape[2], new.shape[2]
    for b in range(old.shape[0]):
        for t in range(old.shape[1]):
            # the counts of the breadcrumbs held: the last w up to the newest's
            for c in range(
                max(int(tail[b, t, T_BASE]) + n[b, t] - w, 0), int(tail[b, t, T_BASE]) + n[b, t]
            ):
                for f in range(3):
                    new[b, t, c & (wn - 1), f] = old[b, t, c & (w - 1), f]


@bare_inline
def push_one(rx, b, ln, ts, st, s):  # pragma: no cover - compiled
    """``StateBuffer.push`` of sender ``s``'s state ``st[:, b, s]`` sent at ``ts`` onto
    link ``ln`` of convoy ``b`` (older than the newest: ignored), then ``Trail.add``, into
    ``rx`` (``Pushed``); only the time where the link keeps no states. ``st``'s rows: the
    plant's (with the heading's cosine and sine, ``vector.plant``) or its first six
    (computed here)."""
    hist, hist_n, newest = rx.hist, rx.hist_n, rx.newest
    if not ts > newest[b, ln]:
        return
    newest[b, ln] = ts
    k = hist.shape[2]
    hist_n[b, ln] = min(hist_n[b, ln] + 1, k)
    if not rx.keeps[ln]:
        return
    for j in range(k - 1, 0, -1):
        for f in range(FIELDS):
            hist[b, ln, j, f] = hist[b, ln, j - 1, f]
    hist[b, ln, 0, T] = ts
    for f in range(5):  # x, y, speed, heading, accel: the plant's rows 0..4
        hist[b, ln, 0, f + 1] = st[f, b, s]
    hist[b, ln, 0, HC], hist[b, ln, 0, HS] = cos_sin(st, b, s)
    tl = rx.trail_of[ln]
    if tl >= 0:
        trail_add(rx.trail, rx.tail, rx.trail_n, b, tl, st[0, b, s], st[1, b, s], rx.spacing,
                  ts, st[2, b, s], hist[b, ln, 0, HC], hist[b, ln, 0, HS])  # fmt: skip
