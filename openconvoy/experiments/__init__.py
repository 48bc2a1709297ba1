"""Experiments: single runs, PER sweeps, experiment files, figures and comparisons.

``runs`` (one seeded simulated run, shared by ``openconvoy sim`` and sweeps), ``sweep``
(experiment files and ``experiment per-sweep``), ``figures`` (a run's plots and the
paper's figures), ``compare`` (two runs or sweeps side by side), ``commands`` (what the
CLI's ``sim``, ``report``, ``presets``, ``experiment`` and ``compare`` do), ``executor``
(where the runs of sweeps, tuning and training execute: local processes, or
``ray_executor``'s Ray cluster), ``portable`` (the files a run reads, shipped to its
worker). Example experiment files are in ``examples/``.
"""

from openconvoy.experiments.runs import RunConfig, RunResult, run_sim

__all__ = ["RunConfig", "RunResult", "run_sim"]
