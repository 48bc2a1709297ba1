"""The training tests need the ``train`` extra (torch, stable-baselines3, SuperSuit,
Optuna, numba for the batched simulator). Without it they are not collected, and the
run's header says so, naming the extra; the rest of the suite collects and runs
(input-defects D12)."""

from __future__ import annotations

import importlib.util

TRAIN_MODULES = ("torch", "stable_baselines3", "supersuit", "optuna", "numba")
MISSING = [m for m in TRAIN_MODULES if importlib.util.find_spec(m) is None]
REASON = f"needs the train extra (pip install 'openconvoy[train]'): {', '.join(MISSING)} missing"


def pytest_ignore_collect(collection_path, config):
    if MISSING and collection_path.name.startswith("test_"):
        return True
    return None


def pytest_report_header(config):
    return f"tests/train skipped: {REASON}" if MISSING else None
