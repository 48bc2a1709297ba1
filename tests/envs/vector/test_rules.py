"""A rule changed in one place changes every world (issue 21): ``ConvoyEnv`` and the
batched kernels of ``VectorConvoyEnv`` both call ``core.spacing``'s functions, the kernels
compiled (``envs.vector.jit.rules``), so replacing one of them moves both worlds alike."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

RUN = Path(__file__).with_name("rule_run.py")
STANDSTILL_M, HEADWAY_S = 2.0, 0.6  # SpacingConfig's defaults, what rule_run uses


def _start(tmp_path: Path, *args: str, cache: Path | None = None) -> tuple[Any, Path]:
    """``rule_run.py`` with ``args`` started in a process of its own: the process and the
    JSON file it writes."""
    out = tmp_path / f"run{'-'.join(args)}.json"
    env = dict(os.environ)
    if cache is not None:  # kernels compiled afresh: the replaced rule is not in the digest
        env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.Popen([sys.executable, str(RUN), str(out), *args], env=env), out


def _result(started: tuple[Any, Path]) -> dict[str, list[float]]:
    """What a started ``rule_run.py`` wrote, once it exits 0."""
    proc, out = started
    assert proc.wait(timeout=900) == 0, f"rule_run.py exited {proc.returncode}"
    return json.loads(out.read_text())


def _headways(run: dict[str, list[float]]) -> list[float]:
    """The headway (s) each tick's desired gap implies, where the follower moves."""
    halves = run["desired"][0] - STANDSTILL_M  # at rest: standstill plus the half lengths
    return [
        (d - STANDSTILL_M - halves) / v for d, v in zip(run["desired"], run["speed"]) if v > 0.2
    ]


@pytest.mark.e2e
def test_replacing_the_time_headway_gap_moves_both_worlds_alike(tmp_path: Path) -> None:
    # Both at once: the doubled run compiles its kernels (~20 CPU-s, nearly all of this
    # test's time) while the plain one runs on the cached kernels on the other core.
    started = _start(tmp_path, "doubled", cache=tmp_path / "kernels"), _start(tmp_path)
    try:
        doubled, plain = _result(started[0]), _result(started[1])
    finally:
        for proc, _ in started:
            proc.kill()  # (a no-op once it has exited)
    # rule_run asserts ConvoyEnv and VectorConvoyEnv agree at every tick in each run; the
    # desired gaps are the rule's own: 0.6 s of headway, then 1.2 s in both worlds
    assert len(_headways(plain)) > 50 and len(_headways(doubled)) > 50
    assert _headways(plain) == pytest.approx([HEADWAY_S] * len(_headways(plain)), abs=1e-9)
    assert _headways(doubled) == pytest.approx([2 * HEADWAY_S] * len(_headways(doubled)), abs=1e-9)
    # and the wider gap changes how the convoy drives: the last follower falls behind
    assert doubled["x"][-1] < plain["x"][-1] - 0.5
