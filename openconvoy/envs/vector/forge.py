"""``forge`` faults in the batched simulator: ``ConvoyWorld._forge`` for every convoy.

As in ``ConvoyEnv`` (``envs.forgery``): from its time on, every tick a keyless forger
broadcasts a state claiming to be vehicle ``ID``, ``FORGED_AHEAD_M`` ahead of where it
really is (the plant's true state, not its GPS fix) along its heading, at its speed, no
acceleration. Its messages do not travel on the simulated channel (no loss draw, no
latency, not in the channel's counters): each tick each other member is offered one.
With authentication on, each fails verification and is counted per receiver
(``forged_rejected``; nothing else changes, so the common path stays fused); with it off,
it is delivered after the channel's messages of the tick, into the R^i buffer of every
receiver whose topology keeps ``ID`` (counted in ``msgs_kept``; not newer than what that
link holds: ignored, as ``StateBuffer.push``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from openconvoy.core.faults import Fault
from openconvoy.envs.forgery import FORGED_AHEAD_M
from openconvoy.envs.vector.jit import bare_kernel
from openconvoy.envs.vector.links import LinkTables
from openconvoy.envs.vector.plant import HEADING, SPEED, X, Y
from openconvoy.envs.vector.rx import RxBuffers, push_one


def first_tick(t_s: float, dt: float) -> int:
    """The first tick ``k`` whose time ``k * dt`` makes a fault at ``t_s`` active
    (``Fault.active``: ``t >= t_s - 1e-9``), by the same float comparison."""
    k = max(0, math.ceil((t_s - 1e-9) / dt))
    while k > 0 and (k - 1) * dt >= t_s - 1e-9:
        k -= 1
    while not k * dt >= t_s - 1e-9:
        k += 1
    return k


class Forgeries(NamedTuple):
    """What ``_forge`` reads and fills: each forger's claimed ``vehicle`` and start time
    ``t_s`` (s), and this tick's forged ``state`` (6, B, N) (scratch)."""

    vehicle: np.ndarray
    t_s: np.ndarray
    state: np.ndarray


class Forgers:
    """The ``forge`` faults among ``faults`` of ``B`` convoys of ``N`` vehicles, ticks of
    ``dt`` s; ``security.auth``: the members verify (reject) forged messages.

    ``delivers``: forged messages reach R^i this run (some forger, authentication off)."""

    def __init__(self, faults: Sequence[Fault], B: int, N: int, dt: float, auth: bool) -> None:
        forged = [f for f in faults if f.forges]
        self.auth = auth
        self.vehicles = np.array([f.vehicle for f in forged], dtype=np.int64)
        self.t_s = np.array([f.t_s for f in forged], dtype=float)
        self.delivers = bool(forged) and not auth
        self._first = [first_tick(f.t_s, dt) for f in forged]
        self._claimed = np.zeros((len(forged), N), dtype=np.int64)  # forger q, receiver r
        for q, f in enumerate(forged):
            self._claimed[q] = np.arange(N) != f.vehicle
        self._state = np.zeros((6, B, N))  # the forged states of this tick (scratch)
        self._forgeries = Forgeries(self.vehicles, self.t_s, self._state)

    def rejected(self, step_count: np.ndarray) -> np.ndarray:
        """Forged messages each member rejected since its convoy's reset, (B, N): one per
        tick ``0..step_count`` from each forger's first one, per receiver not claimed."""
        out = np.zeros((len(step_count), self._claimed.shape[1]), dtype=np.int64)
        if not self.auth:
            return out
        for q, k0 in enumerate(self._first):
            ticks = np.maximum(step_count - k0 + 1, 0)
            out += ticks[:, None] * self._claimed[q]
        return out

    def deliver(
        self,
        t: np.ndarray,
        rows: np.ndarray,
        own: np.ndarray,
        links: LinkTables,
        kept: np.ndarray,
        rx: RxBuffers,
    ) -> None:
        """This tick's forged messages at ``t`` (B,) into ``rx`` for convoys ``rows``, from
        the true states ``own`` (6, B, N); ``kept`` (B, N): messages kept, counted."""
        if not self.delivers:
            return
        _forge(t, rows, own, self._forgeries, links.link_of, kept, rx.pushed)


@bare_kernel
def _forge(t, rows, own, fg, link_of, kept, rx):  # pragma: no cover - compiled
    """``Authentication.deliver_forgeries`` with authentication off: each active forger's
    state (``forgery.forged_state`` of the claimed vehicle's truth) pushed onto every
    receiver's link from the claimed vehicle, in fault order, then receiver order."""
    vehicles, t_s, forged = fg.vehicle, fg.t_s, fg.state
    _, B, N = own.shape
    for b in range(B):
        if not rows[b]:
            continue
        tt = t[b]
        for q in range(len(vehicles)):
            v = vehicles[q]
            if not tt >= t_s[q] - 1e-9:
                continue
            h = own[HEADING, b, v]
            forged[0, b, v] = own[X, b, v] + FORGED_AHEAD_M * math.cos(h)
            forged[1, b, v] = own[Y, b, v] + FORGED_AHEAD_M * math.sin(h)
            forged[2, b, v], forged[3, b, v], forged[4, b, v] = own[SPEED, b, v], h, 0.0
            for r in range(N):  # the leader too: it keeps everyone's for its braking rule
                ln = link_of[v, r]
                if r == v or ln < 0:
                    continue
                kept[b, r] += 1
                push_one(rx, b, ln, tt, forged, v)
