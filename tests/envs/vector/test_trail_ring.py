"""Trails in rings sized to the horizon the observation reads: the same run as rings
that hold every breadcrumb ``Trail`` keeps, through a widening and the oldest-half drop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.core.member import MemberConfig
from openconvoy.envs import VectorConvoyEnv
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vector.trail import CAPACITY, MIN_WINDOW, T_BASE, needs_wider, window
from openconvoy.policies.spec import load_policy


def test_window_is_a_power_of_two_holding_the_horizon_in_three_quarters() -> None:
    assert window(0.0, 0.2, 0.3) == MIN_WINDOW
    assert window(31.0, 0.2, 0.3) == 256  # 155 breadcrumbs: 207 with the margin
    assert window(10_000.0, 0.2, 0.3) == CAPACITY
    assert window(1.0, 0.01, 2.0) == 1024  # 200 breadcrumbs a tick: 4 ticks' worth
    assert needs_wider(193.0, 256) and not needs_wider(192.0, 256)
    assert not needs_wider(5_000.0, CAPACITY)


def _run(start_window: int, monkeypatch: pytest.MonkeyPatch, ticks: int) -> tuple:
    monkeypatch.setattr(VectorConvoyEnv, "_trail_window", lambda self: start_window)
    # Breadcrumbs 8 cm apart (one per delivery at most, 10 a second): the slow paper
    # leader lays over 1,024 of them within the run.
    mc = dataclasses.replace(MemberConfig(spacing=make_scenario("paper").spacing),
                             trail_spacing_m=0.08)  # fmt: skip
    env = VectorConvoyEnv(3, "paper", loss=0.1, max_time_s=200.0, member_config=mc)
    policy = load_policy("paper")
    obs, _ = env.reset(seed=5)
    seen, bases, windows = [], [], []
    for tick in range(ticks):
        obs, rew, *_ = env.step(policy.act_batch(obs))
        if tick % 50 == 0 or tick == ticks - 1:
            seen.append((obs.copy(), rew.copy(), env.own.copy()))
            bases.append(float(env.rx.tail[..., T_BASE].max()))
            windows.append(env.rx.window)
    return seen, bases, windows


def test_a_small_ring_widens_and_runs_as_rings_of_the_whole_capacity(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ticks = 3_400  # the leader's trails pass 1,024 breadcrumbs: their oldest half dropped
    small, bases, windows = _run(MIN_WINDOW, monkeypatch, ticks)
    full, _, full_windows = _run(CAPACITY, monkeypatch, ticks)
    assert set(full_windows) == {CAPACITY}
    assert windows[0] == MIN_WINDOW and MIN_WINDOW < windows[-1] < CAPACITY
    assert bases[-1] >= CAPACITY // 2  # at least one drop
    for (o1, r1, s1), (o2, r2, s2) in zip(small, full):
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(s1, s2)


def test_the_paper_ring_starts_small_and_widens_to_the_reads() -> None:
    """A ring holds a tick's progress at first, then what the reads reach: slow convoys
    (2 m/s, fixed actions) keep small rings, the paper policy's
    formation widens them to the horizon it reads."""
    env = VectorConvoyEnv(2, "paper", loss=0.2)
    assert env.rx.window == MIN_WINDOW == 16  # a tick at 5 m/s: 1.25 breadcrumbs of 0.2 m
    assert env.rx.trail.shape == (2, env.links.T, MIN_WINDOW, 3)
    env.reset(seed=0)
    slow = np.tile(np.array([2.0, 0.0], np.float32), (2, 2, 1))
    for _ in range(200):
        env.step(slow)
    w = env.rx.window  # the smallest ring holding the reads (~40 breadcrumbs back)
    assert 0.75 * w / 2 < env.rx.reach() <= 0.75 * w and w <= 64
    policy = load_policy("paper")
    obs, _ = env.reset(seed=0)
    reach = []
    for _ in range(600):
        obs, *_ = env.step(policy.act_batch(obs))
        reach.append(env.rx.reach())
        assert not needs_wider(env.rx.reach(), env.rx.window)
    assert env.rx.window == 256 and max(reach) > 0.75 * 128  # ~31 m back at 0.2 m


@pytest.mark.e2e
def test_small_rings_run_as_convoy_env_through_a_widening_and_a_drop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Against the reference: ``Trail``'s 1,024 breadcrumbs and its oldest-half drop
    (``_compare`` asserts every tick's observations, states, counters and modes)."""
    from tests.envs.vector.test_vector_env import _compare

    monkeypatch.setattr(VectorConvoyEnv, "_trail_window", lambda self: MIN_WINDOW)
    seen: list[tuple[int, float]] = []
    step = VectorConvoyEnv.step

    def watched(self: VectorConvoyEnv, actions: np.ndarray) -> tuple:
        out = step(self, actions)
        seen.append((self.rx.window, float(self.rx.tail[..., T_BASE].max())))
        return out

    monkeypatch.setattr(VectorConvoyEnv, "step", watched)
    _compare(B=1, per=0.1, member={"trail_spacing_m": 0.08}, max_time_s=200.0, steps=3_400)
    assert seen[0][0] == MIN_WINDOW and max(w for w, _ in seen) > MIN_WINDOW
    assert max(base for _, base in seen) >= CAPACITY // 2


def test_widening_in_place_moves_every_held_breadcrumb_to_its_slot_and_zeroes_the_rest() -> None:
    """``RxBuffers.widen`` grows the rings within their own buffer: each breadcrumb the
    old ring held (count ``c`` since the reset) lands in slot ``c mod`` the new size of its
    own trail's ring, whatever the trails' counts and bases; every other slot is zero."""
    env = VectorConvoyEnv(3, "paper", loss=0.2)
    rx = env.rx
    B, T, w, _ = rx.trail.shape
    rng = np.random.default_rng(4)
    rx.trail[...] = rng.random(rx.trail.shape) + 1.0  # nothing zero: a stale slot would show
    rx.trail_n[...] = rng.integers(0, 3 * w, size=(B, T))
    rx.tail[..., T_BASE] = rng.integers(0, 2, size=(B, T)) * (CAPACITY // 2)
    old = rx.trail.copy()
    rx.widen(4 * w)
    assert rx.trail.shape == (B, T, 4 * w, 3) and rx.pushed.trail is rx.trail
    expected = np.zeros((B, T, 4 * w, 3))
    for b in range(B):
        for t in range(T):
            last = int(rx.tail[b, t, T_BASE]) + int(rx.trail_n[b, t]) - 1
            for c in range(max(last - w + 1, 0), last + 1):
                expected[b, t, c % (4 * w)] = old[b, t, c % w]
    np.testing.assert_array_equal(rx.trail, expected)
