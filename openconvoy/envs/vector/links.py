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
    """The tables for ``N`` vehicles under ``mc``'s topology and observation layout.

    Each receiver's kept senders come from ``RxGate.kept_row`` (in bulk for a built-in
    topology, a plug-in's ``keeps`` per sender otherwise); the tables are numpy work,
    no Python loop over vehicle pairs."""
    lay = mc.layout
    kept = np.zeros((N, N), dtype=bool)  # kept[r, s]: ρ(r, s), the leader keeps none
    for r in range(1, N):
        kept[r] = RxGate(mc.topology, r, N, mc.topology_params).kept_row()
    ids = np.arange(N)
    # Links (receiver-major, senders ascending): ρ's, each follower's predecessor and
    # the leader's from everyone.
    mask = kept.copy()
    mask[ids[1:], ids[1:] - 1] = True
    mask[0, 1:] = True
    mask[ids, ids] = False
    link_r, link_s = np.nonzero(mask)
    L = len(link_r)
    link_of = np.full((N, N), -1, dtype=np.int64)
    link_of[link_s, link_r] = np.arange(L, dtype=np.int64)
    control = np.where(kept.T, link_of, -1)  # the links ρ keeps, [s, r]
    # Each receiver's needed links: the kept predecessors, nearest first.
    needed = [link_of[np.flatnonzero(kept[r, :r])[::-1], r] for r in range(N)]
    width = max(1, max(len(v) for v in needed))
    need = np.full((N, width), -1, dtype=np.int64)
    for r, v in enumerate(needed):
        need[r, : len(v)] = v
    del needed
    F = N - 1
    i = ids[1:]
    slot_link = np.full((F, len(lay.slots)), -1, dtype=np.int64)
    target_link = np.full((F, len(lay.targets)), -1, dtype=np.int64)
    # Slots: the leader, predecessors 1..M, the follower behind.
    slot_vid = [np.zeros(F, dtype=np.int64), *(i - m for m in range(1, lay.M + 1))]
    slot_vid.append(np.where(i + 1 < N, i + 1, -1))
    for k, vid in enumerate(slot_vid):
        ok = vid >= 0
        slot_link[ok, k] = control[vid[ok], i[ok]]
    for k in range(len(lay.targets)):
        vid = np.zeros(F, dtype=np.int64) if k == 0 else i - k
        ok = (vid >= 0) & ~((k == 0) & (i <= lay.M))
        target_link[ok, k] = control[vid[ok], i[ok]]
    pred_link = link_of[i - 1, i].copy()
    lead_link = link_of[:, 0].copy()
    keeps_states = np.zeros(max(L, 1), dtype=bool)
    for table in (slot_link, target_link, pred_link, lead_link):
        keeps_states[table[table >= 0]] = True
    trail_of = np.full(max(L, 1), -1, dtype=np.int64)
    targets = np.unique(target_link[target_link >= 0])
    trail_of[targets] = np.arange(len(targets))
    return LinkTables(
        N=N,
        L=L,
        link_s=link_s.astype(np.int64),
        link_r=link_r.astype(np.int64),
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
