"""The tasks of a sweep: one ``ConvoyEnv`` run each, or a policy's runs in a few batches.

Where the batched env takes a policy's runs (``batched.refusal``), they become
``batches`` tasks of consecutive runs (at least as many as the executor has slots, each
at most ``MAX_BATCH_CELLS`` ticks × vehicles × convoys), each a ``VectorConvoyEnv``
(``batched.run_batch``) that returns every run's files, metrics and figure series as a
per-run task would; ``expand_one`` turns a task's result back into one per run, a failed
batch into a failure of each of its runs. Other policies' runs are one task each.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openconvoy.experiments import portable
from openconvoy.experiments.executor import Task, TaskFailure, report_progress
from openconvoy.experiments.portable import Files
from openconvoy.experiments.runs import EVENTS_FILE, RunConfig, run_sim

RUN_FILES = ("log.csv", "metrics.json")
MAX_BATCH_CELLS = 2_000_000
"""Ticks × vehicles × convoys of one batch: its recorder holds about 16 arrays of that
many 8-byte values (the paper scenario: 555 convoys, 256 MB)."""


def run_one(args: tuple[RunConfig, Files, bool, bool]) -> dict[str, Any]:
    """Task: one run in a temporary directory of its worker; returns its files as bytes
    (``logs``: with its ``log.csv``; ``events.json`` when it had events), its metrics and
    (``keep_series``) the figure series. The driver writes the files."""
    from openconvoy.experiments.sweep import run_series

    config, files, keep_series, logs = args
    with tempfile.TemporaryDirectory(prefix="openconvoy-run-") as tmp:
        where = portable.land(files, tmp)
        out = Path(tmp) / "run"
        with portable.driver_names(where):
            result = run_sim(portable.relocate_run(config, where), out)
        names = RUN_FILES[1 - logs :] + ((EVENTS_FILE,) if result.events else ())
        return {
            "files": {name: (out / name).read_bytes() for name in names},
            "metrics": result.metrics,
            "series": run_series(result.log, result.lengths) if keep_series else None,
        }


def run_many(args: tuple[list[RunConfig], Files, list[bool], bool]) -> list[dict[str, Any]]:
    """Task: runs differing only in PER and seed, batched (``batched.run_batch``); what
    ``run_one`` returns, for each (``logs``: with its ``log.csv``)."""
    from openconvoy.experiments.batched.run import run_batch

    configs, files, series, logs = args
    with tempfile.TemporaryDirectory(prefix="openconvoy-batch-") as tmp:
        where = portable.land(files, tmp)
        with portable.driver_names(where):
            local = [portable.relocate_run(c, where) for c in configs]
            return run_batch(
                local, read_back=True, logs=logs, series=series, on_progress=report_progress
            )


@dataclass
class SweepTasks:
    """The tasks of a sweep's runs: ``spans[i]`` = (first run, runs) of ``tasks[i]``;
    ``per_run``: policy label -> why its runs are not batched (when asked to be)."""

    tasks: list[Task] = field(default_factory=list)
    spans: list[tuple[int, int]] = field(default_factory=list)
    per_run: dict[str, str] = field(default_factory=dict)


def plan(
    planned: Sequence[tuple[str, RunConfig]],
    dirs: Sequence[str],
    series: Sequence[bool],
    slots: int,
    batched: bool | None = None,
    logs: bool = True,
) -> SweepTasks:
    """Tasks for ``planned`` (ordered by policy): a policy's runs batched unless
    ``batched`` is False or ``batched.refusal`` (exact: ``batched`` None) says why not."""
    from openconvoy.experiments.batched.run import refusal

    out = SweepTasks()
    for label, first, n in _groups(planned):
        configs = [rc for _, rc in planned[first : first + n]]
        why = "not asked to" if batched is False else refusal(configs[0], exact=batched is None)
        if why is None:
            _batches(out, configs, dirs, series, first, slots, logs)
            continue
        if batched is not False:
            out.per_run[label] = why
        for i in range(first, first + n):
            rc = planned[i][1]
            out.tasks.append(
                Task(dirs[i], run_one, (rc, portable.ship(portable.run_specs(rc)), series[i], logs))
            )
            out.spans.append((i, 1))
    return out


def _groups(planned: Sequence[tuple[str, RunConfig]]) -> list[tuple[str, int, int]]:
    """(policy label, first run, runs) of each policy's consecutive runs."""
    out: list[tuple[str, int, int]] = []
    for i, (label, _) in enumerate(planned):
        if out and out[-1][0] == label:
            out[-1] = (label, out[-1][1], out[-1][2] + 1)
        else:
            out.append((label, i, 1))
    return out


def _batches(
    out: SweepTasks,
    configs: list[RunConfig],
    dirs: Sequence[str],
    series: Sequence[bool],
    first: int,
    slots: int,
    logs: bool,
) -> None:
    from openconvoy.experiments.batched.run import batch_cells

    n = len(configs)
    size = max(1, min(math.ceil(n / max(1, slots)), MAX_BATCH_CELLS // batch_cells(configs[0])))
    files = portable.ship(portable.run_specs(configs[0]))
    for start in range(0, n, size):
        part = configs[start : start + size]
        i = first + start
        label = f"{dirs[i]} .. {dirs[i + len(part) - 1]} (batch of {len(part)})"
        out.tasks.append(
            Task(label, run_many, (part, files, list(series[i : i + len(part)]), logs))
        )
        out.spans.append((i, len(part)))


def expand_one(result: Any, n: int, dirs: Sequence[str]) -> list[Any]:
    """The results of one task's ``n`` runs (named ``dirs``): a failed batch is a failure
    of each of its runs."""
    if n == 1 and not isinstance(result, list):
        return [result]
    if isinstance(result, TaskFailure):
        return [TaskFailure(d, result.where, result.error) for d in dirs]
    return list(result[:n])


def say_per_run(plan: SweepTasks, say: Callable[[str], None]) -> None:
    """One line per policy whose runs are not batched though they might have been."""
    for label, why in plan.per_run.items():
        say(f"{label}: one ConvoyEnv per run ({why})")
