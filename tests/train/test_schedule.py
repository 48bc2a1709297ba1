"""A run's clock, learning rate and PER curriculum (``openconvoy.train.schedule``), and the
wall-clock budget stopping a real training run in time."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from openconvoy.train.config import PPOConfig, TrainConfig
from openconvoy.train.randomization import EnvSpec, Randomization
from openconvoy.train.schedule import (
    FIRST_VALIDATION_GUESS_S,
    RESERVE_MARGIN_S,
    RunClock,
    curriculum_per_high,
    linear_schedule,
)
from openconvoy.train.train import train


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_progress_is_the_further_of_steps_and_time() -> None:
    t = FakeClock()
    clock = RunClock(1000, budget_s=100.0, clock=t)
    learn = 100.0 - RESERVE_MARGIN_S - 2 * FIRST_VALIDATION_GUESS_S
    assert clock.learn_budget_s() == pytest.approx(learn)
    assert clock.progress(500) == 0.5  # steps ahead
    t.now += learn * 0.8
    assert clock.progress(500) == pytest.approx(0.8) and not clock.out_of_time()
    # A timed validation sizes the reserve: 30 s validations keep 60 s and the margin.
    clock.timed_validation(30.0)
    clock.timed_validation(1.0)
    assert clock.reserve_s == RESERVE_MARGIN_S + 60.0
    assert clock.out_of_time() and clock.progress(500) == 1.0
    # Without a budget only the steps count, and the clock never stops a run.
    free = RunClock(1000, budget_s=None, clock=t)
    t.now += 1e6
    assert free.progress(250) == 0.25 and not free.out_of_time()
    # A run without a final validation keeps only the margin.
    assert RunClock(10, 60.0, clock=t, validates=False).reserve_s == RESERVE_MARGIN_S


def test_learning_rate_decays_with_the_clock_when_it_is_ahead() -> None:
    t = FakeClock()
    clock = RunClock(1000, budget_s=RESERVE_MARGIN_S + 2 * FIRST_VALIDATION_GUESS_S + 10, clock=t)
    lr = linear_schedule(1e-3, clock)
    assert lr(1.0) == pytest.approx(1e-3) and lr(0.25) == pytest.approx(2.5e-4)
    t.now += 5.0  # half the learning budget
    assert lr(0.9) == pytest.approx(5e-4)
    t.now += 50.0
    assert lr(0.9) == 0.0


def test_progress_never_goes_back_when_a_timed_validation_shrinks_the_reserve() -> None:
    t = FakeClock()
    clock = RunClock(10**6, budget_s=100.0, clock=t)
    lr = linear_schedule(1e-3, clock)
    t.now += 40.0  # 40 s of a 65 s learning budget (the first reserve is a guess)
    progress, rate = clock.progress(0), lr(1.0)
    cap = curriculum_per_high(progress, (0.0, 0.6), 1.0)
    clock.timed_validation(1.0)  # the reserve drops to 7 s: 93 s to learn
    assert clock.progress(0) >= progress and lr(1.0) <= rate
    assert curriculum_per_high(clock.progress(0), (0.0, 0.6), 1.0) >= cap
    t.now += 53.0 - 1e-9  # just before the new learning budget ends: still going, nearly 1
    assert not clock.out_of_time() and 0.99 < clock.progress(0) < 1.0
    t.now += 1e-6
    assert clock.out_of_time() and clock.progress(0) == 1.0 and lr(1.0) == 0.0


def test_curriculum_raises_the_per_cap_linearly_then_holds() -> None:
    r = (0.0, 0.6)
    assert [curriculum_per_high(p, r, 0.5) for p in (0.0, 0.25, 0.5, 0.9)] == pytest.approx(
        [0.0, 0.3, 0.6, 0.6]
    )
    assert curriculum_per_high(0.0, r, 0.0) == 0.6  # no curriculum: the full range
    assert curriculum_per_high(0.5, (0.1, 0.5), 1.0) == pytest.approx(0.3)


def _tiny(**changes) -> TrainConfig:
    base = dict(
        env=EnvSpec(base_policy="", max_time_s=2.0),
        randomization=Randomization(vehicles=()),
        n_envs=2,
        n_worlds=1,
        checkpoint_every=0,
        validation_seeds=(),
    )
    return TrainConfig(**{**base, **changes})


def test_curriculum_raises_per_high_during_training(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A real PPO run: the training env's PER cap follows the schedule, step by step,
    from the first worlds it trains on."""
    from openconvoy.train.vecenv import randomized as batched

    caps_drawn: list[float] = []  # the cap of every world the env drew
    draw = batched.draw_group

    def recorded(*args, **kwargs):
        caps_drawn.append(args[-1])
        return draw(*args, **kwargs)

    monkeypatch.setattr(batched, "draw_group", recorded)
    config = _tiny(
        total_steps=2048,
        per_curriculum=0.5,
        randomization=Randomization(vehicles=(), per_range=(0.1, 0.5)),
    )
    config = dataclasses.replace(config, ppo=PPOConfig(n_steps=64))
    train(config, tmp_path / "run", progress_bar=False)
    record = json.loads((tmp_path / "run" / "train.json").read_text())["per_high"]
    steps = [s for s, _ in record]
    caps = [v for _, v in record]
    assert steps[0] == 0 and caps[0] == pytest.approx(0.1)
    assert caps == sorted(caps) and caps[-1] == pytest.approx(0.5)  # rises, ends at the top
    for s, v in record:  # on schedule: linear over the first half of the run
        assert v == pytest.approx(curriculum_per_high(s / 2048, (0.1, 0.5), 0.5), abs=1e-4)
    assert any(0.1 < v < 0.5 for v in caps)
    # The constructor's world (full range) is redrawn by learn()'s first reset: the
    # worlds trained on start at the bottom of the range and rise.
    assert caps_drawn[1] == pytest.approx(0.1) and caps_drawn[1:] == sorted(caps_drawn[1:])


def test_budget_stops_learning_in_time(tmp_path: Path) -> None:
    """A 10^9-step run with a wall-clock budget of the margin plus 3 s stops learning
    after about 3 s and still writes its policy."""
    config = _tiny(total_steps=10**9, budget_s=RESERVE_MARGIN_S + 3.0)
    result = train(config, tmp_path / "run", progress_bar=False)
    summary = json.loads((tmp_path / "run" / "train.json").read_text())
    assert result.stopped_by_budget and summary["stopped_by_budget"] is True
    assert 0 < result.steps < 10**9 and 2.5 < result.wall_s < 3.0 + 2.0
    assert result.policy_path.exists()
