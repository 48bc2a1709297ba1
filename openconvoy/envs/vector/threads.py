"""The fused tick on every core it is given: the batch cut into slabs of convoys, one
thread each.

A convoy's tick reads and writes its own rows only (its random draws are counter-based
on its own keys, ``comms.loss``), so slabs of convoys stepped at once give the same
numbers, bit for bit, whatever the thread count (``tests/envs/vector/test_threads.py``).
The kernels release the GIL (``vector.jit``: ``nogil``), so plain threads run them in
parallel; no thread pool inside numba, and no scratch shared between slabs.

A slab's arguments are views of the env's arrays: each array is cut along its convoy
axis (the one of length ``B``; the plant's flat rows, ``B * N``); arrays without one
(the link tables, the presets' constants) are shared read-only; the kernels' scratch is
copied per slab. The lengths of the arrays without convoys must differ from ``B`` so
that the axis is unambiguous; otherwise (or for a small batch) the tick runs whole on
one thread.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

MIN_SLAB = 512
"""Fewest convoys a thread gets: below, a thread's start (~30 µs) costs more than the
slab's tick (at 512 convoys of 3 vehicles, ~1.5 ms on one core)."""


def thread_count(threads: int | None) -> int:
    """Threads a batched step may use: ``threads``, or the cores this process may run on
    (``os.sched_getaffinity``: what ``taskset`` gives it) capped by numba's
    ``NUMBA_NUM_THREADS`` when that is set."""
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads: expected a positive integer, got {threads!r}")
        return threads
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cap = os.environ.get("NUMBA_NUM_THREADS")
    n = cores or 1
    if cap and cap.strip().isdigit() and int(cap) > 0:
        n = min(n, int(cap))
    return max(1, n)


def slab_bounds(B: int, threads: int) -> list[tuple[int, int]]:
    """Contiguous ``[b0, b1)`` slabs of ``B`` convoys for at most ``threads`` threads,
    each at least ``MIN_SLAB`` convoys (one slab: no split)."""
    n = max(1, min(threads, B // MIN_SLAB))
    edges = [B * j // n for j in range(n + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _cut(arr: np.ndarray, B: int, N: int, b0: int, b1: int) -> np.ndarray:
    """``arr``'s rows of convoys ``b0..b1``: along its first axis of length ``B`` (the
    convoy axis comes before the per-convoy ones: ``(B, ...)`` or ``(rows, B, ...)``),
    else its first of length ``B * N`` (the plant's flat rows), else all of it (shared)."""
    for size, lo, hi in ((B, b0, b1), (B * N, b0 * N, b1 * N)):
        if size in arr.shape:
            index = [slice(None)] * arr.ndim
            index[arr.shape.index(size)] = slice(lo, hi)
            return arr[tuple(index)]
    return arr


def cut_args(
    args: Any,
    B: int,
    N: int,
    b0: int,
    b1: int,
    private: Sequence[np.ndarray],
    copies: dict[int, np.ndarray],
) -> Any:
    """``args`` (nested tuples and NamedTuples of arrays and scalars) for convoys ``b0..b1``: arrays cut
    (``_cut``), the ``private`` ones copied (once each; ``copies`` maps the original's
    ``id`` to its copy), scalars as they are."""
    if isinstance(args, tuple):
        items = [cut_args(a, B, N, b0, b1, private, copies) for a in args]
        # a NamedTuple of named state stays one (the kernels read it by name)
        return type(args)(*items) if hasattr(args, "_fields") else tuple(items)
    if isinstance(args, np.ndarray):
        if any(args is p for p in private):
            return copies.setdefault(id(args), args.copy())
        return _cut(args, B, N, b0, b1)
    return args


def structural_sizes(env: Any) -> set[int]:
    """Lengths of the env's arrays without convoys (link tables, scratch, the leaders'
    path segments): one equal to ``B`` (or ``B * N``) would be taken for a convoy axis."""
    lk = env.links
    N = env.n_vehicles
    sizes = {N, N - 1, N + 1, N * N, lk.L, lk.T, len(env.channel.pair_s)}
    tables = (lk.needed, lk.slot_link, lk.target_link, env._targets_scratch, env.leader.road.seg)
    for arr in tables:
        sizes.update(arr.shape)
    return sizes


class Slabs:
    """The fused tick of one env cut into slabs run on threads (``step``); built only
    where there is more than one slab."""

    def __init__(
        self,
        bounds: list[tuple[int, int]],
        packs: list[Any],
        calls: list[Any],
        mirrors: list[tuple[np.ndarray, np.ndarray]],
    ) -> None:
        self.bounds, self.packs, self.calls = bounds, packs, calls
        # (env's array, slab 0's copy): state every slab advances alike (the plant's
        # ring head), copied back so the env's stays current.
        self.mirrors = mirrors
        self._pool: ThreadPoolExecutor | None = None
        self._warm = False

    def step(self, a: np.ndarray, obs: np.ndarray, rewards: np.ndarray,
             terminated: np.ndarray, truncated: np.ndarray,
             filled: tuple[np.ndarray, ...]) -> None:  # fmt: skip
        """The fused tick of every slab (``fused_step``'s per-step arrays, whole)."""
        jobs = []
        for (b0, b1), pack, call in zip(self.bounds, self.packs, self.calls):
            cut = tuple(f[:, b0:b1] for f in filled)
            jobs.append((call, (a[b0:b1], obs[b0:b1], rewards[b0:b1], terminated[b0:b1],
                                truncated[b0:b1], cut, pack)))  # fmt: skip
        if not self._warm:  # the first call types (or compiles) the kernels: one at a time
            for call, args in jobs:
                call(*args)
            self._warm = True
        else:
            self._parallel(jobs)
        for whole, copy in self.mirrors:
            whole[...] = copy

    def _parallel(self, jobs: list[tuple[Any, tuple[Any, ...]]]) -> None:
        """Run ``jobs`` (call, arguments) at once: the first on this thread."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(len(jobs) - 1, thread_name_prefix="openconvoy-slab")
        futures = [self._pool.submit(call, *args) for call, args in jobs[1:]]
        call, args = jobs[0]
        call(*args)
        for fut in futures:
            fut.result()

    def close(self) -> None:
        """Stop the threads (a later ``step`` starts them again)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def make_slabs(env: Any, fused: Any, threads: int, call_factory: Any) -> Slabs | None:
    """``Slabs`` for ``env``'s packed stages ``fused`` on ``threads`` threads, or None
    where the tick runs whole (one slab, or an array without convoys whose length is
    ``B``: it would be taken for a convoy axis)."""
    B, N = env.num_envs, env.n_vehicles
    bounds = slab_bounds(B, threads)
    if len(bounds) < 2 or {B, B * N} & structural_sizes(env):
        return None
    # Copied per slab: the kernels' scratch, and the plant's ring head (each slab's
    # plant step advances its own).
    head = env.plant.head
    private = [env._targets_scratch, env.channel._zs, head]
    copies: list[dict[int, np.ndarray]] = [{} for _ in bounds]
    packs = [cut_args(fused, B, N, b0, b1, private, c) for (b0, b1), c in zip(bounds, copies)]
    mirrors = [(head, copies[0][id(head)])]
    return Slabs(bounds, packs, [call_factory() for _ in bounds], mirrors)
