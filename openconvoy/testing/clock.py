"""A monotonic clock for tests: time moves only when somebody sleeps (or sets it)."""

from __future__ import annotations

WALL0 = 1.7e9
"""The wall clock (Unix seconds) at monotonic time 0 of a ``FakeClock``."""


class FakeClock:
    """Monotonic time (s) that only moves when somebody sleeps (or sets ``t``): give the
    instance as ``clock``, its ``sleep`` as ``sleep`` and its ``wall`` as ``wall_clock``
    to a ``DeployRunner``, and a run of minutes takes milliseconds, the same every time."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        """The monotonic time now (s)."""
        return self.t

    def sleep(self, dt: float) -> None:
        """Move on by ``dt`` seconds (a negative ``dt`` moves nothing)."""
        self.t += max(dt, 0.0)

    def wall(self) -> float:
        """The wall-clock time now (Unix s): ``WALL0`` plus the monotonic time."""
        return WALL0 + self.t


__all__ = ["WALL0", "FakeClock"]
