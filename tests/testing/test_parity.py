"""``openconvoy.testing.parity``: equality to the bit, and trees compared file by file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from openconvoy.testing import same, tree_files


def test_same_is_equality_to_the_bit_with_nan_equal_to_nan() -> None:
    a = {"obs": (np.array([1.0, np.nan], dtype=np.float32), [math.nan, 2])}
    assert same(a, {"obs": (np.array([1.0, np.nan], dtype=np.float32), [math.nan, 2])})
    assert not same(a, {"obs": (np.array([1.0, np.nan]), [math.nan, 2])})  # float64
    assert not same(a, {"obs": (np.array([1.0, 0.0], dtype=np.float32), [math.nan, 2])})
    assert not same(a, {"obs": (np.array([1.0, np.nan], dtype=np.float32), [math.nan])})
    assert not same(a, {"other": 1}) and not same(math.nan, 1.0)
    assert same(0.1 + 0.2, 0.1 + 0.2) and not same(0.1 + 0.2, 0.3)


def test_same_compares_object_arrays_element_by_element() -> None:
    modes = np.array(["coop", "hold"], dtype=object)
    assert same(modes, np.array(["coop", "hold"], dtype=object))
    assert not same(modes, np.array(["coop", "stop"], dtype=object))
    assert not same(modes, np.array(["coop", "hold"]))  # a fixed-width string array


def test_tree_files_holds_every_file_but_the_skipped(tmp_path: Path) -> None:
    (tmp_path / "run" / "a").mkdir(parents=True)
    (tmp_path / "run" / "a" / "log.csv").write_bytes(b"t\n1\n")
    (tmp_path / "run" / "manifest.json").write_text("{}")
    (tmp_path / "run" / "summary.csv").write_bytes(b"x")
    files = tree_files(tmp_path / "run", skip=("manifest.json",))
    assert files == {"a/log.csv": b"t\n1\n", "summary.csv": b"x"}
    assert list(files) == sorted(files)
    assert "manifest.json" in tree_files(tmp_path / "run")
