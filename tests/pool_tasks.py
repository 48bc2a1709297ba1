"""Tasks for the local process pool's tests, in a module of their own so the spawned
workers import nothing else (the test modules pull in the whole package)."""

from __future__ import annotations

import os


def square_or_die(x: int) -> int:
    """The worker process given 3 dies without a word (as a segfault would)."""
    if x == 3:
        os._exit(7)
    return x * x
