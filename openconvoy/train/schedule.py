"""A run's progress through its budgets, and what follows it: the learning rate, the PER
curriculum, and stopping in time.

A run has a step budget (``total_steps``) and, optionally, a wall-clock budget
(``budget_s``) covering the whole ``train`` call: learning stops early enough that the
final validation and the run directory still fit (``RunClock.reserve_s``: twice the
longest checkpoint validation seen, plus a margin). Progress is the further of the two,
0 -> 1, so a run cut by its clock still decays its learning rate to (nearly) 0 and
finishes its curriculum, as a run of the steps it managed would have. Progress never goes
back: when a timed validation shrinks the reserve (the first one is a guess), the clock's
share waits until the longer learning budget catches up with it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

RESERVE_MARGIN_S = 5.0
"""Seconds kept for saving the final network, ``policy.json`` and ``train.json``."""
FIRST_VALIDATION_GUESS_S = 15.0
"""The reserve's guess at a validation's length before one has been timed (s)."""


class RunClock:
    """Progress through ``total_steps`` and ``budget_s`` (None: no clock), from
    ``start`` (``clock()`` seconds; ``clock`` is injectable for tests); ``validates``:
    whether the run ends with a validation (the reserve keeps time for it)."""

    def __init__(
        self,
        total_steps: int,
        budget_s: float | None,
        clock: Callable[[], float] = time.perf_counter,
        validates: bool = True,
    ) -> None:
        self.total_steps = total_steps
        self.budget_s = budget_s
        self.validates = validates
        self.clock = clock
        self.start = clock()
        self.longest_validation_s = 0.0
        self._time_progress = 0.0  # the furthest time_progress so far

    def elapsed_s(self) -> float:
        return self.clock() - self.start

    @property
    def reserve_s(self) -> float:
        """Seconds kept at the end of the budget for the final validation and files."""
        if not self.validates:
            return RESERVE_MARGIN_S
        longest = self.longest_validation_s or FIRST_VALIDATION_GUESS_S
        return RESERVE_MARGIN_S + 2.0 * longest

    def learn_budget_s(self) -> float | None:
        """Seconds of the budget learning may use (None: no clock)."""
        if self.budget_s is None:
            return None
        return max(0.0, self.budget_s - self.reserve_s)

    def time_progress(self) -> float:
        """How far the clock is through the learning budget, 0 -> 1 (0 without one),
        never less than before (a shrinking reserve lengthens the budget)."""
        learn = self.learn_budget_s()
        if learn is None:
            return 0.0
        now = min(1.0, self.elapsed_s() / learn) if learn > 0 else 1.0
        self._time_progress = max(self._time_progress, now)
        return self._time_progress

    def progress(self, steps: int) -> float:
        """How far the run is, 0 -> 1: the further of steps and (with a budget) time."""
        return min(1.0, max(steps / self.total_steps, self.time_progress()))

    def out_of_time(self) -> bool:
        learn = self.learn_budget_s()
        return learn is not None and self.elapsed_s() >= learn

    def timed_validation(self, seconds: float) -> None:
        """Record a checkpoint validation's length (it sizes the reserve)."""
        self.longest_validation_s = max(self.longest_validation_s, seconds)


def linear_schedule(value: float, clock: RunClock) -> Callable[[float], float]:
    """SB3 schedule: ``value`` decaying linearly to 0 over the run's progress (steps or
    clock, whichever is further)."""

    def schedule(remaining: float) -> float:
        # SB3's ``remaining`` (1 -> 0) counts steps only; the clock may be further along.
        return value * max(0.0, min(remaining, 1.0 - clock.time_progress()))

    return schedule


def curriculum_per_high(progress: float, per_range: tuple[float, float], span: float) -> float:
    """The PER cap at ``progress`` (0 -> 1) of a curriculum that raises it linearly from
    ``per_range[0]`` to ``per_range[1]`` over the first ``span`` of the run (0: no
    curriculum, the full range from the start)."""
    lo, hi = per_range
    if span <= 0:
        return hi
    return lo + (hi - lo) * min(1.0, progress / span)


def _unwrapped(venv: VecEnv) -> VecEnv:
    while isinstance(venv, VecEnvWrapper):
        venv = venv.venv
    return venv


class Schedule(BaseCallback):
    """Follows ``clock`` during ``learn``: stops learning when the clock's learning budget
    is spent, and (``span`` > 0) raises the training PER cap ``per_high`` on schedule
    (``curriculum_per_high``; the batched simulator only: elsewhere one stderr line says
    the curriculum is not applied)."""

    def __init__(self, clock: RunClock, per_range: tuple[float, float], span: float) -> None:
        super().__init__()
        self.clock = clock
        self.per_range = per_range
        self.span = span
        self.stopped_by_clock = False
        self.per_high: list[tuple[int, float]] = []
        """(steps, per_high) at every change, for the run's record."""

    def prime(self, venv: VecEnv) -> None:
        """Before ``learn``: set ``venv``'s PER cap to the curriculum's start, so that the
        worlds ``learn``'s first reset draws (before any callback runs) follow it."""
        if self.span > 0 and hasattr(_unwrapped(venv), "per_high"):
            venv.set_attr("per_high", curriculum_per_high(0.0, self.per_range, self.span))

    def _on_training_start(self) -> None:
        if self.span > 0 and not hasattr(_unwrapped(self.training_env), "per_high"):
            print(
                "openconvoy train: the PER curriculum needs the batched simulator; "
                "training on the full PER range",
                file=sys.stderr,
            )
            self.span = 0.0
        self._apply()

    def _apply(self) -> None:
        if self.span <= 0:
            return
        value = curriculum_per_high(
            self.clock.progress(self.num_timesteps), self.per_range, self.span
        )
        if not self.per_high or self.per_high[-1][1] != value:
            self.training_env.set_attr("per_high", value)
            self.per_high.append((int(self.num_timesteps), value))
            self.logger.record("train/per_high", value)

    def _on_rollout_end(self) -> None:
        self._apply()

    def _on_step(self) -> bool:
        if self.clock.out_of_time():
            self.stopped_by_clock = True
            return False
        return True
