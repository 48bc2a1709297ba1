"""The batched simulator's static structure: which links a topology keeps, and where
each link's data lands in a follower's observation (index tables built once)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openconvoy.core.gates import RxGate
from openconvoy.core.member import MemberConfig


@dataclass(frozen=True)
class LinkTables:
    """Kept links (receiver >= 1, sender) of an ``N``-vehicle convoy, and index tables.

    ``link_of[s, r]``: link index or -1; ``needed[r]``: links whose age sets receiver
    ``r``'s ladder rung, padded with -1; ``slot_link[f, slot]``, ``target_link[f, target]``
    (follower ``f + 1``, layout order): link or -1 (the leader as a target only when
    not a predecessor slot); ``pred_link[f]``: the link to the immediate predecessor;
    ``lead_link[j]``: the leader's link from vehicle ``j`` (-1 for ``j`` = 0). Besides
    the links ρ keeps, every follower keeps its predecessor's and the leader everyone's
    for the braking rule (``ConvoyMember``): such a link feeds no slot, target or age.
    What a link's receiver reads of it: ``keeps_states[ln]``, its last ``k`` states (a
    slot, a target or the predecessor), else only the newest message's time (the
    ladder's age); ``trail_of[ln]``, its trail's row (a target), else -1, of ``T``.
    """

    N: int
    L: int
    link_s: np.ndarray
    link_r: np.ndarray
    link_of: np.ndarray
    needed: np.ndarray
    slot_link: np.ndarray
    target_link: np.ndarray
    pred_link: np.ndarray
    lead_link: np.ndarray
    keeps_states: np.ndarray
    trail_of: np.ndarray
    T: int


def build_links(mc: MemberConfig, N: int) -> LinkTables:
    """The tables for ``N`` vehicles under ``mc``'s topology and observation layout."""
    lay = mc.layout
    links: list[tuple[int, int]] = []
    link_of = np.full((N, N), -1, dtype=np.int64)
    needed: list[list[int]] = [[] for _ in range(N)]
    control = np.full((N, N), -1, dtype=np.int64)  # the links ρ keeps
    for r in range(N):
        gate = RxGate(mc.topology, r, N, mc.topology_params)
        for s in range(N):
            kept = gate.keeps(s) if r > 0 else False
            if s != r and (kept or s == r - 1 or r == 0):
                link_of[s, r] = len(links)
                if kept:
                    control[s, r] = len(links)
                links.append((r, s))
        if r > 0:
            needed[r] = [int(link_of[j, r]) for j in gate.needed()]
    width = max(1, max(len(v) for v in needed))
    need = np.full((N, width), -1, dtype=np.int64)
    for r, v in enumerate(needed):
        need[r, : len(v)] = v
    F = N - 1
    slot_link = np.full((F, len(lay.slots)), -1, dtype=np.int64)
    target_link = np.full((F, len(lay.targets)), -1, dtype=np.int64)
    for i in range(1, N):
        preds = [i - m if i - m >= 0 else -1 for m in range(1, lay.M + 1)]
        for k, vid in enumerate([0, *preds, i + 1 if i + 1 < N else -1]):
            if vid >= 0:
                slot_link[i - 1, k] = control[vid, i]
        for k in range(len(lay.targets)):
            vid = 0 if k == 0 else i - k
            if vid >= 0 and not (k == 0 and i <= lay.M):
                target_link[i - 1, k] = control[vid, i]
    pred_link = np.array([link_of[i - 1, i] for i in range(1, N)], dtype=np.int64)
    lead_link = link_of[:, 0].copy()
    keeps_states = np.zeros(max(len(links), 1), dtype=bool)
    for table in (slot_link, target_link, pred_link, lead_link):
        keeps_states[table[table >= 0]] = True
    trail_of = np.full(max(len(links), 1), -1, dtype=np.int64)
    targets = np.unique(target_link[target_link >= 0])
    trail_of[targets] = np.arange(len(targets))
    return LinkTables(
        N=N,
        L=len(links),
        link_s=np.array([s for _, s in links], dtype=np.int64),
        link_r=np.array([r for r, _ in links], dtype=np.int64),
        link_of=link_of,
        needed=need,
        slot_link=slot_link,
        target_link=target_link,
        pred_link=pred_link,
        lead_link=lead_link,
        keeps_states=keeps_states,
        trail_of=trail_of,
        T=len(targets),
    )
