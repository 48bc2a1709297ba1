"""``experiments.runs``: how a simulated run times its policies (``UnloadedClock``)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from openconvoy.experiments.runs import UnloadedClock


def _spin(seconds_of_work: int) -> None:
    x = 0
    for i in range(seconds_of_work):
        x += i * i


def test_a_sleep_counts_as_on_an_idle_machine():
    clock = UnloadedClock()
    try:
        t0 = clock()
        time.sleep(0.2)
        took = clock() - t0
    finally:
        clock.close()
    assert 0.19 < took < 0.3


def test_waiting_for_a_core_does_not_count():
    """On one core shared with a busy process, the wall clock sees the work take about
    twice as long; the run's clock sees about what it takes alone."""
    cores = os.sched_getaffinity(0)
    core = min(cores)
    os.sched_setaffinity(0, {core})
    busy = subprocess.Popen(
        [sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{core}}})\nwhile True: pass"]
    )
    clock = UnloadedClock()
    try:
        time.sleep(0.3)  # the competitor is running
        w0, c0 = time.perf_counter(), clock()
        _spin(3_000_000)
        wall, unloaded = time.perf_counter() - w0, clock() - c0
    finally:
        busy.kill()
        busy.wait()
        clock.close()
        os.sched_setaffinity(0, cores)
    assert unloaded < 0.75 * wall, (unloaded, wall)


def test_without_schedstat_it_is_the_wall_clock(tmp_path):
    clock = UnloadedClock(str(tmp_path / "absent"))
    t0, w0 = clock(), time.perf_counter()
    assert abs(t0 - w0) < 0.01
    clock.close()
    clock.close()  # idempotent
