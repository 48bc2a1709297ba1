"""Several ``openconvoy train`` runs (seeds, configurations) as tasks of an executor.

``openconvoy train --seeds 0 1 2 [--config A.toml --config B.toml] --out DIR`` makes one
run per (config, seed): ``DIR/seed_<S>`` for seeds alone, ``DIR/<config stem>`` for
configs alone, ``DIR/<config stem>/seed_<S>`` for both (one config alone, sent to a
cluster with ``--executor ray``: ``DIR`` itself). Each run trains in a temporary
directory of its worker (``openconvoy.train.train.train``, unchanged); its whole run
directory comes back to the driver as bytes and only the driver writes ``DIR`` (no file
system shared with the workers). ``DIR/runs.json`` lists the runs: name, seed, steps, wall
time, where it ran, or its error.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openconvoy.core.errors import ConfigError, OutputPathError
from openconvoy.experiments import portable
from openconvoy.experiments.executor import (
    Executor,
    Task,
    TaskFailure,
    TasksFailed,
    worker_location,
)
from openconvoy.train.config import TrainConfig

# Files of a run directory that record paths: the worker's are replaced by the driver's.
RELOCATED_FILES = ("config.toml", "validation.json", "policy.json", "train.json")


@dataclass(frozen=True)
class TrainRun:
    """One training run: its directory name under the output and its config."""

    name: str
    config: TrainConfig


def plan(configs: Sequence[tuple[str, TrainConfig]], seeds: Sequence[int] | None) -> list[TrainRun]:
    """One run per (config, seed) (no seeds: each config's own), named as the module says."""
    runs = []
    for stem, config in configs:
        if not seeds:
            # One config alone (sent to a cluster): the output directory is its run directory.
            runs.append(TrainRun(stem if len(configs) > 1 else ".", config))
            continue
        for seed in seeds:
            name = f"seed_{seed}" if len(configs) == 1 else f"{stem}/seed_{seed}"
            runs.append(TrainRun(name, dataclasses.replace(config, seed=int(seed))))
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise ConfigError(
            f"training runs would share a directory: {', '.join(sorted(names))}; "
            "give configs distinct file names and seeds distinct values"
        )
    return runs


def train_specs(config: TrainConfig) -> list[str]:
    """The specs of a TrainConfig that may name files (base policy, presets, scenarios)."""
    r = config.randomization
    return [config.env.base_policy, *r.vehicles, *r.scenarios]


def _relocated(config: TrainConfig, where: dict[str, str]) -> TrainConfig:
    if not where:
        return config
    env = dataclasses.replace(
        config.env, base_policy=portable.relocate(config.env.base_policy, where)
    )
    r = config.randomization
    r = dataclasses.replace(
        r,
        vehicles=tuple(portable.relocate(v, where) for v in r.vehicles),
        scenarios=tuple(portable.relocate(s, where) for s in r.scenarios),
    )
    return dataclasses.replace(config, env=env, randomization=r)


def train_on_worker(args: tuple[TrainConfig, portable.Files]) -> dict[str, Any]:
    """Task: one training run in a temporary directory; returns its files (relative
    path -> bytes; in the files that record paths, the run directory is ``{RUN_DIR}`` and
    shipped files have their driver names), steps and wall time."""
    from openconvoy.train.train import train

    config, files = args
    with tempfile.TemporaryDirectory(prefix="openconvoy-train-") as tmp:
        where = portable.land(files, tmp)
        run_dir = Path(tmp) / "run"
        with portable.driver_names(where):
            result = train(_relocated(config, where), run_dir, progress_bar=False)
        out = {}
        for path in sorted(p for p in run_dir.rglob("*") if p.is_file()):
            rel = path.relative_to(run_dir).as_posix()
            data = path.read_bytes()
            if rel in RELOCATED_FILES:
                data = _replace_paths(
                    data, {str(run_dir): "{RUN_DIR}", **{w: d for d, w in where.items()}}
                )
            out[rel] = data
        return {
            "files": out,
            "steps": result.steps,
            "wall_s": result.wall_s,
            "where": worker_location(),
        }


def _replace_paths(data: bytes, paths: dict[str, str]) -> bytes:
    """``data`` (JSON or TOML text) with each path in ``paths`` replaced, as written in
    those formats' strings (the same escaping for both)."""
    for old, new in paths.items():
        data = data.replace(json.dumps(old)[1:-1].encode(), json.dumps(new)[1:-1].encode())
    return data


def train_many(
    runs: Sequence[TrainRun],
    out_dir: str | Path,
    executor: Executor,
    progress: bool = True,
    overwrite: bool = False,
) -> list[dict[str, Any]]:
    """Train ``runs`` as tasks of ``executor`` and write each run directory under
    ``out_dir`` (and ``runs.json``); raises TasksFailed after writing the runs that
    finished when some did not."""
    from openconvoy.train.train import POLICY_FILE

    out = Path(out_dir)
    for run in runs:
        if (out / run.name / POLICY_FILE).exists() and not overwrite:
            raise OutputPathError(
                f"{out / run.name} already holds a trained policy; choose another --out or --overwrite"
            )
    tasks = [
        Task(run.name, train_on_worker, (run.config, portable.ship(train_specs(run.config))))
        for run in runs
    ]
    with executor:
        results = executor.map(tasks, progress, desc="train")
    summary, failures = [], []
    for run, res in zip(runs, results):
        entry: dict[str, Any] = {"name": run.name, "seed": run.config.seed}
        if isinstance(res, TaskFailure):
            failures.append(res)
            entry["error"] = res.line()
        else:
            run_dir = out / run.name
            for rel, data in res["files"].items():
                path = run_dir / rel
                path.parent.mkdir(parents=True, exist_ok=True)
                if rel in RELOCATED_FILES:
                    data = _replace_paths(data, {"{RUN_DIR}": str(run_dir.resolve())})
                path.write_bytes(data)
            entry.update(
                steps=res["steps"],
                wall_s=round(res["wall_s"], 3),
                ran_on=res["where"],
                policy=(Path(run.name) / POLICY_FILE).as_posix(),
            )
        summary.append(entry)
    out.mkdir(parents=True, exist_ok=True)
    (out / "runs.json").write_text(json.dumps({"runs": summary}, indent=1) + "\n", encoding="utf-8")
    if failures:
        raise TasksFailed(
            failures, len(runs), f"the other {len(runs) - len(failures)} are in {out}"
        )
    return summary
