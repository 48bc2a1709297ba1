"""Tasks for the local process pool's tests, in a module of their own so the spawned
workers import nothing else (the test modules pull in the whole package)."""

from __future__ import annotations

import os


def square_or_die(x: int) -> int:
    """The worker process given 3 dies without a word (as a segfault would)."""
    if x == 3:
        os._exit(7)
    return x * x


def report_quarters(x: int) -> int:
    """Reports a quarter, a half, a quarter again (backwards: ignored) and three quarters
    done, then waits a second (the driver reads the reports meanwhile) and returns x."""
    import time

    from openconvoy.experiments.executor import report_progress

    for fraction in (0.25, 0.5, 0.25, 0.75):
        report_progress(fraction)
    time.sleep(1.0)
    return x
