"""The simulated channel: loss per link, bursts, latency and its counters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.comms.loss import LossConfig, LossReplay, quantile_delay
from openconvoy.core.state import VehicleState
from openconvoy.envs import ConvoyEnv
from openconvoy.envs.channel import Channel, advance_state
from tests.python_world import python_world  # noqa: F401 - reads the Python world


def _binomial_band(n: int, p: float, z: float = 2.576) -> tuple[float, float]:
    """99 % normal-approximation band of a binomial proportion."""
    half = z * math.sqrt(p * (1 - p) / n)
    return p - half, p + half


def test_perfect_links_deliver_everything_to_everyone_else() -> None:
    ch: Channel[str] = Channel(4)
    ch.reset(np.random.default_rng(0))
    ch.send(1, "hello", 0.0)
    got = ch.deliver(0.0)
    assert sorted((r, s) for r, s, _ in got) == [(0, 1), (2, 1), (3, 1)]
    assert ch.deliver(0.1) == []
    assert ch.sent[1].tolist() == [1, 0, 1, 1]
    assert ch.delivered[1].tolist() == [1, 0, 1, 1]
    assert ch.lost.sum() == 0
    assert ch.delivery_ratio() == 1.0
    assert ch.delivered_to == [1, 0, 1, 1]


def test_bernoulli_delivery_ratio_in_binomial_band() -> None:
    per = 0.3
    ch: Channel[int] = Channel(3, LossConfig(per=per))
    ch.reset(np.random.default_rng(1))
    for k in range(5000):
        ch.send(k % 3, k, k * 0.01)
        ch.deliver(k * 0.01)
    n = int(ch.sent.sum())
    assert n == 10000
    lo, hi = _binomial_band(n, 1 - per)
    assert lo <= ch.delivery_ratio() <= hi
    # Every link loses independently at the same rate.
    for s in range(3):
        for r in range(3):
            if s != r:
                ratio = ch.delivered[s, r] / ch.sent[s, r]
                lo, hi = _binomial_band(int(ch.sent[s, r]), 1 - per)
                assert lo <= ratio <= hi
    assert ch.delivered_to == ch.delivered.sum(axis=0).tolist()
    assert ch.lost_to == ch.lost.sum(axis=0).tolist()


def test_links_to_different_receivers_are_independent() -> None:
    ch: Channel[int] = Channel(3, LossConfig(per=0.5))
    ch.reset(np.random.default_rng(2))
    got_1, got_2 = [], []
    for k in range(4000):
        ch.send(0, k, k * 0.1)
        arrived = {r for r, _, _ in ch.deliver(k * 0.1)}
        got_1.append(1 in arrived)
        got_2.append(2 in arrived)
    a, b = np.array(got_1, float), np.array(got_2, float)
    # Independent: the correlation is near 0 (it would be 1 for one shared draw).
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.06


def _run_lengths(lost: list[bool]) -> list[int]:
    runs, k = [], 0
    for x in lost:
        if x:
            k += 1
        elif k:
            runs.append(k)
            k = 0
    return runs


def test_gilbert_elliott_loses_in_bursts_at_the_configured_rate() -> None:
    per, burst_s, period = 0.3, 1.0, 0.1
    ch: Channel[int] = Channel(
        2, LossConfig(per=per, model="gilbert-elliott", mean_burst_s=burst_s)
    )
    ch.reset(np.random.default_rng(3))
    lost = []
    for k in range(30000):
        t = k * period
        ch.send(0, k, t)
        lost.append(not ch.deliver(t))
    rate = float(np.mean(lost))
    assert rate == pytest.approx(per, abs=0.04)
    runs = _run_lengths(lost)
    # Mean burst of 1 s at 10 Hz: about 10 packets per burst (independent loss: 1 / (1 - per)).
    assert np.mean(runs) > 6.0
    bern: Channel[int] = Channel(2, LossConfig(per=per))
    bern.reset(np.random.default_rng(3))
    lost_b = []
    for k in range(30000):
        bern.send(0, k, k * period)
        lost_b.append(not bern.deliver(k * period))
    assert np.mean(_run_lengths(lost_b)) == pytest.approx(1 / (1 - per), rel=0.1)


def test_latency_delays_delivery_and_keeps_arrival_order() -> None:
    ch: Channel[int] = Channel(2, LossConfig(latency_s=0.1))
    ch.reset(np.random.default_rng(0))
    for k in range(5):
        ch.send(0, k, k * 0.05)
    assert ch.deliver(0.05) == []
    assert ch.in_flight == 5
    assert [m for _, _, m in ch.deliver(0.1)] == [0]  # sent at 0, due at 0.1
    assert [m for _, _, m in ch.deliver(0.2)] == [1, 2]
    assert [m for _, _, m in ch.deliver(1.0)] == [3, 4]
    assert ch.in_flight == 0


def test_jitter_delivers_in_arrival_time_order_within_bounds() -> None:
    base, jitter = 0.05, 0.2
    ch: Channel[float] = Channel(2, LossConfig(latency_s=base, jitter_s=jitter))
    ch.reset(np.random.default_rng(5))
    sent_at = [k * 0.01 for k in range(200)]
    for t in sent_at:
        ch.send(0, t, t)
    arrivals = []
    now = 0.0
    while now < 3.0:
        for _, _, t_sent in ch.deliver(now):
            arrivals.append((now, t_sent))
        now += 0.01
    assert len(arrivals) == 200
    delays = [a - s for a, s in arrivals]
    assert min(delays) >= base - 1e-9
    assert max(delays) <= base + jitter + 0.01 + 1e-9
    # Jitter reorders some messages (sent later, arrived earlier).
    order = [s for _, s in arrivals]
    assert order != sorted(order)


def test_reset_clears_queue_and_counters_and_same_rng_repeats() -> None:
    ch: Channel[int] = Channel(3, LossConfig(per=0.5, latency_s=0.5))
    ch.reset(np.random.default_rng(9))
    for k in range(50):
        ch.send(k % 3, k, 0.0)
    first = ch.lost.copy()
    ch.reset(np.random.default_rng(9))
    assert ch.in_flight == 0 and ch.sent.sum() == 0
    for k in range(50):
        ch.send(k % 3, k, 0.0)
    assert np.array_equal(first, ch.lost)


def test_rejects_empty_channel() -> None:
    with pytest.raises(ValueError, match="at least one vehicle"):
        Channel(0)


def test_sub_tick_latency_gives_that_message_age_at_first_use() -> None:
    """A 0.034 s delay on a 0.05 s tick: delivered at the tick, advanced by the 0.016 s it
    waited (2 m/s, 1 m/s², turning), so its age there is 0.034 s, not a whole tick."""
    ch: Channel[VehicleState] = Channel(2, LossConfig(latency_s=0.034), advance_state)
    ch.reset(np.random.default_rng(0))
    sent = VehicleState(0, 0.0, 1.0, 2.0, 2.0, 0.0, accel=1.0, yaw_rate=0.5)
    ch.send(0, sent, 0.0)
    assert ch.deliver(0.0) == []
    ((r, s, got),) = ch.deliver(0.05)
    assert (r, s) == (1, 0)
    assert 0.05 - got.t == pytest.approx(0.034, abs=1e-12)
    d = 0.016
    assert got.speed == pytest.approx(2.0 + 1.0 * d)
    assert got.heading == pytest.approx(0.5 * d)
    assert math.hypot(got.x - 1.0, got.y - 2.0) == pytest.approx(2.0 * d + 0.5 * d * d)
    # Braking through zero stops there rather than reversing.
    stopping = advance_state(VehicleState(0, 0.0, 0.0, 0.0, 0.01, 0.0, accel=-1.0), 0.04)
    assert stopping.speed == 0.0 and 0.0 <= stopping.x <= 0.01 * 0.04


def test_latency_samples_are_drawn_as_their_distribution() -> None:
    samples = (0.01, 0.02, 0.06)  # quantiles at 0, 1/2, 1
    assert quantile_delay(samples, 0.0) == 0.01
    assert quantile_delay(samples, 0.25) == pytest.approx(0.015)
    assert quantile_delay(samples, 0.75) == pytest.approx(0.04)
    ch: Channel[int] = Channel(2, LossConfig(latency_samples_s=(0.06, 0.01, 0.02)))
    ch.reset(np.random.default_rng(1))
    for k in range(4000):
        ch.send(0, k, k * 1.0)
    delays = []
    for k in range(4000):
        due = [a for a, *_ in ch._queue if a < k + 0.5]
        delays += [a - k for a in due]
        ch.deliver(k + 0.5)
    d = np.array(delays)
    assert d.min() >= 0.01 and d.max() <= 0.06
    assert np.mean(d < 0.02) == pytest.approx(0.5, abs=0.03)
    assert d.mean() == pytest.approx((0.015 + 0.04) / 2, abs=0.002)


def test_latency_samples_are_checked() -> None:
    with pytest.raises(ValueError, match="latency samples"):
        LossConfig(latency_samples_s=(0.01, -0.2))
    with pytest.raises(ValueError, match="not both"):
        LossConfig(jitter_s=0.1, latency_samples_s=(0.01,))


def test_convoy_env_message_age_follows_a_sub_tick_latency() -> None:
    """The sim's logged predecessor message age at first use is the latency (0.034 s), and
    the next tick's 0.084 s: the same pattern as vehicle logs (sitl/convoy vx-fixed-1)."""
    env = ConvoyEnv("paper", loss=LossConfig(latency_s=0.034))
    env.reset(seed=0)
    ages = []
    for _ in range(60):
        _, _, _, _, info = env.step({a: np.array([1.0, 0.0], np.float32) for a in env.agents})
        ages.append(info["follower_1"]["pred_msg_age_s"])
    got = sorted({round(a, 6) for a in ages[5:]})
    assert got == [0.034, 0.084]


def test_each_link_can_have_its_own_delay_distribution() -> None:
    loss = LossConfig(latency_samples_s=(0.05,), link_latency_s=((0, 1, 0.034), (1, 2, 0.02, 0.03)))
    ch: Channel[VehicleState] = Channel(3, loss, advance_state)
    ch.reset(np.random.default_rng(0))
    ch.send(0, VehicleState(0, 0.0, 0.0, 0.0, 1.0, 0.0), 0.0)
    ch.send(1, VehicleState(1, 0.0, -15.0, 0.0, 1.0, 0.0), 0.0)
    ages = {(s, r): round(0.05 - m.t, 6) for r, s, m in ch.deliver(0.05)}
    assert ages[(0, 1)] == 0.034 and ages[(0, 2)] == 0.05 and ages[(1, 0)] == 0.05
    assert 0.02 <= ages[(1, 2)] <= 0.03
    with pytest.raises(ValueError, match="sender, receiver"):
        LossConfig(link_latency_s=((0, 0, 0.1),))
    with pytest.raises(ValueError, match="twice"):
        LossConfig(link_latency_s=((0, 1, 0.1), (0, 1, 0.2)))


def test_a_senders_clock_error_ages_its_messages() -> None:
    """A clock 0.1 s + 10 ms/s behind: messages sent at t claim t - 0.1 - 0.01 t."""
    ch: Channel[VehicleState] = Channel(
        2, LossConfig(stamp_error_s=0.1, stamp_drift=0.01), advance_state
    )
    ch.reset(np.random.default_rng(0))
    ch.send(0, VehicleState(0, 10.0, 0.0, 0.0, 2.0, 0.0), 10.0)
    ((_, _, got),) = ch.deliver(10.0)
    assert got.t == pytest.approx(10.0 - 0.2) and got.x == 0.0


def test_loss_draws_do_not_depend_on_how_many_broadcasts_are_drawn_at_once(monkeypatch) -> None:
    """A long convoy draws fewer broadcasts ahead (``DRAW_BUDGET``): the same drops, which
    are ``counter_uniform`` of (key, sender, receiver, broadcast number)."""
    import openconvoy.envs.channel as channel_mod
    from openconvoy.comms.loss import counter_uniform

    n, per, sends = 12, 0.3, 20

    def drops(budget: int) -> list[list[int]]:
        monkeypatch.setattr(channel_mod, "DRAW_BUDGET", budget)
        ch: Channel[int] = Channel(n, LossConfig(per=per))
        ch.reset(np.random.default_rng(5))
        for k in range(sends):
            for s in range(n):
                ch.send(s, k, 0.05 * k)
        return ch.lost.tolist()

    assert channel_mod.draw_block_size(1001) == 4 and channel_mod.draw_block_size(3) == 64
    one_at_a_time, many = drops(n - 1), drops(10**6)
    assert one_at_a_time == many
    ch: Channel[int] = Channel(n, LossConfig(per=per))
    ch.reset(np.random.default_rng(5))
    want = [
        [
            0 if s == r else sum(counter_uniform(ch.key, s, r, k, 0) < per for k in range(sends))
            for r in range(n)
        ]
        for s in range(n)
    ]
    assert many == want and 0 < sum(map(sum, want)) < n * (n - 1) * sends


def test_a_senders_staleness_ages_only_its_own_messages() -> None:
    """Staleness 30 ms for vehicle 0, none for 1, on top of a 0.1 s clock error: sent at
    t = 10 and delivered 7 ms later, 0's messages are 0.137 s old at first use, 1's
    0.107 s; the delay (7 ms) is the link's alone."""
    cfg = LossConfig(latency_s=0.007, stamp_error_s=0.1, staleness_s=(0.03,))
    assert cfg.link_latency(0, 1).stamp_error_s == pytest.approx(0.13)
    assert cfg.link_latency(1, 0).stamp_error_s == pytest.approx(0.1)
    ch: Channel[VehicleState] = Channel(2, cfg, advance_state)
    ch.reset(np.random.default_rng(0))
    ch.send(0, VehicleState(0, 10.0, 0.0, 0.0, 2.0, 0.0), 10.0)
    ch.send(1, VehicleState(1, 10.0, -15.0, 0.0, 2.0, 0.0), 10.0)
    assert ch.deliver(10.0) == []
    got = {s: m for _, s, m in ch.deliver(10.05)}
    assert 10.05 - got[0].t == pytest.approx(0.137) and 10.05 - got[1].t == pytest.approx(0.107)
    assert got[0].x == pytest.approx(2.0 * 0.043)  # advanced by its wait for the tick only
    staleness_only = Channel(2, LossConfig(staleness_s=(0.0, 0.02)), advance_state)
    staleness_only.reset(np.random.default_rng(0))
    staleness_only.send(1, VehicleState(1, 5.0, 0.0, 0.0, 1.0, 0.0), 5.0)
    ((_, _, m),) = staleness_only.deliver(5.0)
    assert m.t == pytest.approx(4.98)
    with pytest.raises(ValueError, match="staleness_s"):
        LossConfig(staleness_s=(-0.1,))


def test_a_link_replays_a_runs_recorded_losses() -> None:
    """0 -> 1 dropped the broadcasts sent at 0.2 and 0.5 s on the run: the sim's broadcasts
    nearest them (within half the 0.1 s period) are dropped, the rest delivered even at a
    PER of 0.9; the other links still draw (1 -> 0 loses most at 0.9)."""
    replay = LossReplay((0.2, 0.5), 0.05)
    assert [replay.lost(t) for t in (0.1, 0.16, 0.2, 0.24, 0.3, 0.5)] == [
        False, True, True, True, False, True,
    ]  # fmt: skip
    cfg = LossConfig(per=0.9, lost_s=((0, 1, 0.5, 0.2),), lost_window_s=0.05)
    assert cfg.lost_s == ((0.0, 1.0, 0.2, 0.5),)
    ch: Channel[VehicleState] = Channel(2, cfg)
    ch.reset(np.random.default_rng(0))
    heard = []
    for k in range(10):
        t = 0.1 * k
        ch.send(0, VehicleState(0, t, 0.0, 0.0, 1.0, 0.0), t)
        ch.send(1, VehicleState(1, t, 0.0, 0.0, 1.0, 0.0), t)
        heard += [(s, round(m.t, 1)) for _, s, m in ch.deliver(t)]
    assert [t for s, t in heard if s == 0] == [0.0, 0.1, 0.3, 0.4, 0.6, 0.7, 0.8, 0.9]
    assert ch.lost[0, 1] == 2 and ch.delivered[0, 1] == 8
    assert ch.lost[1, 0] + ch.delivered[1, 0] == 10 and ch.lost[1, 0] >= 6
    assert ch.lost_to == [ch.lost[1, 0], 2]
    with pytest.raises(ValueError, match="twice"):
        LossConfig(lost_s=((0, 1, 0.2), (0, 1)))
    with pytest.raises(ValueError, match="lost_window_s"):
        LossConfig(lost_window_s=0.0)


def test_the_batched_channel_refuses_a_replay() -> None:
    from openconvoy.envs import VectorConvoyEnv

    with pytest.raises(ValueError, match="replaying"):
        VectorConvoyEnv(1, loss=LossConfig(per=0.3, lost_s=((0, 1, 0.2),)))
