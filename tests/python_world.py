"""Tests that read ``ConvoyEnv``'s Python world (``sim``, ``members``, ``channel``, log
rows, plans) import ``python_world``: their envs take the Python path (the reference,
what vehicles run) whatever the default backend (``envs.compiled``)."""

from __future__ import annotations

import pytest

from openconvoy.envs.compiled import BACKEND_ENV_VAR


@pytest.fixture(autouse=True)
def python_world(monkeypatch: pytest.MonkeyPatch) -> None:
    """``ConvoyEnv(...)`` without a ``backend`` is the Python path in this module."""
    monkeypatch.setenv(BACKEND_ENV_VAR, "python")
