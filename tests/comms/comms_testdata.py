"""Shared test data for the comms tests (imported by name: tests/comms is on sys.path)."""

from __future__ import annotations

import json
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
VECTORS_PATH = REPO_ROOT / "tests" / "data" / "interop" / "j2735-bsm-vectors.json"


def load_vectors() -> list[dict]:
    """The 54 interop frames of tests/data/interop (see tests/data/README.md)."""
    if not VECTORS_PATH.is_file():
        raise FileNotFoundError(f"interop vectors not found at {VECTORS_PATH}")
    return json.loads(VECTORS_PATH.read_text())
