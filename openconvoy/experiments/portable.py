"""Files a run reads on the driver, shipped to its worker as bytes.

A spec may name a file: a policy ``.toml``/``.zip``/``.npz`` (with ``+ladder`` too), a
plug-in's ``file.py:Name``, a vehicle preset ``.toml``, a scenario ``track-file:PATH``
(files a policy TOML names inside, plug-ins' ``file.py``, are not shipped: give workers on
other machines the plug-in as an installed module). A worker on another machine
has no such file, so the driver reads each one (``ship``) and the worker writes them into
its own temporary directory (``land``) and runs with the specs pointing there
(``relocate``). A run's results do not depend on where its files lie.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from openconvoy.core.plugins import split_args
from openconvoy.policies.spec import PolicySpec

TRACK_PREFIX = "track-file:"
FILE_SUFFIXES = (".toml", ".zip", ".npz", ".json")

Files = dict[str, bytes]


def spec_file(spec: str) -> str | None:
    """The file a policy, preset or scenario spec names, or None for a built-in name."""
    if not spec:
        return None
    if spec.startswith(TRACK_PREFIX):
        return spec[len(TRACK_PREFIX) :]
    parsed = PolicySpec.parse(spec)
    if parsed.plugin_file is not None:  # a plug-in's own file.py:Name
        return parsed.plugin_file
    base = split_args(parsed.base)[0]
    return base if base.endswith(FILE_SUFFIXES) else None


def ship(specs: Iterable[str]) -> Files:
    """The bytes of every file ``specs`` name, by the name the driver knows it by."""
    files: Files = {}
    for spec in specs:
        path = spec_file(spec)
        if path is not None and path not in files:
            files[path] = Path(path).read_bytes()
    return files


def land(files: Files, directory: str | Path) -> dict[str, str]:
    """Write shipped files under ``directory``; driver name -> worker path."""
    out: dict[str, str] = {}
    root = Path(directory) / "shipped"
    for i, (name, data) in enumerate(sorted(files.items())):
        # Own subdirectory each: files of the same name from different places stay apart,
        # and a policy keeps its file name (its stem is the policy's default name).
        path = root / str(i) / Path(name).name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        out[name] = str(path)
    return out


def relocate(spec: str, where: dict[str, str]) -> str:
    """``spec`` with its file (if shipped) replaced by the worker's copy."""
    path = spec_file(spec)
    if path is None or path not in where:
        return spec
    if spec.startswith(TRACK_PREFIX):
        return TRACK_PREFIX + where[path]
    return where[path] + spec[len(path) :]


@contextmanager
def driver_names(where: dict[str, str]) -> Iterator[None]:
    """Errors raised inside name the driver's files, not the worker's copies."""
    try:
        yield
    except Exception as exc:
        back = {worker: driver for driver, worker in where.items()}

        def rename(value: object) -> object:
            if not isinstance(value, str):
                return value
            for worker, driver in back.items():
                value = value.replace(worker, driver)
            return value

        exc.args = tuple(rename(a) for a in exc.args)
        if isinstance(exc, OSError) and exc.filename is not None:
            exc.filename = rename(exc.filename)
        raise


def run_specs(config: Any) -> list[str]:
    """The specs of a ``RunConfig`` that may name files."""
    return [config.policy, config.scenario, *config.convoy.vehicles]


def relocate_run(config: Any, where: dict[str, str]) -> Any:
    """A ``RunConfig`` reading the worker's copies of its files."""
    if not where:
        return config
    return dataclasses.replace(
        config,
        policy=relocate(config.policy, where),
        scenario=relocate(config.scenario, where),
        convoy=dataclasses.replace(
            config.convoy, vehicles=tuple(relocate(v, where) for v in config.convoy.vehicles)
        ),
    )
