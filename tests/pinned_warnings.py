"""Upstream checkers' warnings, pinned: a checker test fails on any warning not on its
allow-list (as Gymnasium's and HighwayEnv's own tests do), so a new warning is a decision,
not noise."""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

UNBOUNDED = "positions, speeds and gaps have no bound; the layout's flags, ages and angles do"

PETTINGZOO_ALLOWED: Mapping[str, str] = {
    r"minimum observation space value is -infinity": UNBOUNDED,
    r"maximum observation space value is infinity": UNBOUNDED,
    r"Observation numpy array is all zeros": "a follower at rest that heard nobody yet (30 % loss at t = 0)",
}
GYMNASIUM_ALLOWED: Mapping[str, str] = {
    r"observation space minimum value is -infinity": UNBOUNDED,
    r"observation space maximum value is infinity": UNBOUNDED,
    r"symmetric and normalized (space|Box action space)": "actions are SI units by design (DESIGN.md, Action); "
    "learners normalize in a wrapper",
    r"not having a spec": "checked on the instance; gymnasium.make is tested beside it",
}


@contextmanager
def pinned(allowed: Mapping[str, str]) -> Iterator[list[str]]:
    """Record every warning inside; fail on one no ``allowed`` pattern (regex -> why it is
    expected) matches. Yields the messages seen."""
    seen: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield seen
    seen.extend(f"{w.category.__name__}: {w.message}" for w in caught)
    unexpected = [m for m in seen if not any(re.search(p, m) for p in allowed)]
    assert not unexpected, "warnings not on the allow-list:\n" + "\n".join(unexpected)
