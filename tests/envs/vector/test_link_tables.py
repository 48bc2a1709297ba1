"""The batched simulator's link tables: built in bulk, equal to the per-pair reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.core.gates import RxGate
from openconvoy.core.member import MemberConfig
from openconvoy.envs import VectorConvoyEnv
from openconvoy.envs.vector.links import LinkTables, build_links


def _reference(mc: MemberConfig, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Links (receiver-major), ``link_of`` and the needed links, asking ρ pair by pair."""
    links, link_of = [], np.full((N, N), -1, dtype=np.int64)
    needed: list[list[int]] = [[] for _ in range(N)]
    for r in range(N):
        gate = RxGate(mc.topology, r, N, mc.topology_params)
        for s in range(N):
            kept = gate.keeps(s) if r > 0 else False
            if s != r and (kept or s == r - 1 or r == 0):
                link_of[s, r] = len(links)
                links.append((r, s))
        if r > 0:
            needed[r] = [int(link_of[j, r]) for j in gate.needed()]
    return (
        np.array([s for _, s in links], dtype=np.int64),
        np.array([r for r, _ in links], dtype=np.int64),
        link_of,
        needed,
    )


def _check(tables: LinkTables, mc: MemberConfig, N: int) -> None:
    link_s, link_r, link_of, needed = _reference(mc, N)
    np.testing.assert_array_equal(tables.link_s, link_s)
    np.testing.assert_array_equal(tables.link_r, link_r)
    np.testing.assert_array_equal(tables.link_of, link_of)
    for r, v in enumerate(needed):
        row = tables.needed[r]
        assert row[row >= 0].tolist() == v


TOPOLOGIES = ["predecessor", "all-predecessors", "lookahead:2", "lookahead:N", "leader",
              "leader-predecessor", "bidirectional", "all"]  # fmt: skip


@pytest.mark.parametrize("topology", TOPOLOGIES)
@pytest.mark.parametrize("N", [1, 2, 3, 7])
def test_links_equal_the_per_pair_reference(topology: str, N: int) -> None:
    mc = MemberConfig(topology=topology, M=3)
    _check(build_links(mc, N), mc, N)


def test_a_plugin_topology_gives_the_tables_of_its_builtin_twin() -> None:
    builtin = MemberConfig(topology="all-predecessors")
    plugin = MemberConfig(topology="tests/data/plugins/equal.py:AllPredecessors")
    a, b = build_links(builtin, 9), build_links(plugin, 9)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y


def test_a_long_builtin_convoy_is_built_without_asking_rho_per_pair(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Issue 28: 300 all-predecessor followers once asked keeps() ~90k times (a million
    # at 1,000); a built-in topology answers each receiver's senders in bulk.
    calls = []
    keeps = RxGate.keeps
    monkeypatch.setattr(RxGate, "keeps", lambda self, j: calls.append(j) or keeps(self, j))
    env = VectorConvoyEnv(1, "paper", n_followers=300, loss=0.2)
    env.reset(seed=0)
    assert calls == []
    assert env.links.L == 301 * 300 // 2 + 300  # the kept links and the leader's
