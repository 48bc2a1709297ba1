"""Experiments: single runs, PER sweeps, experiment files, figures and comparisons.

``runs`` (one seeded simulated run, shared by ``openconvoy sim`` and sweeps), ``sweep``
(experiment files and ``experiment per-sweep``), ``figures`` (a run's plots and the
paper's figures), ``compare`` (two runs or sweeps side by side), ``fitplant`` and ``recording`` (vehicle
presets fitted from logs and MAVLink recordings: ``fit-plant``), ``cli`` (the commands'
parsers), ``commands`` (what the
CLI's ``sim``, ``report``, ``presets``, ``experiment`` and ``compare`` do), ``executor``
(where the runs of sweeps, tuning and training execute: local processes, or
``ray_executor``'s Ray cluster), ``portable`` (the files a run reads, shipped to its
worker). Example experiment files are in ``examples/``.
"""

from typing import Any

__all__ = ["RunConfig", "RunResult", "run_sim"]


def __getattr__(name: str) -> Any:
    # Lazy, so that ``experiments.cli`` (imported to build ``openconvoy``'s parser) does not
    # pull in the simulator.
    if name in __all__:
        from openconvoy.experiments import runs

        return getattr(runs, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
