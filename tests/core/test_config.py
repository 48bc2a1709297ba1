"""``core.config.dumps_toml``: what it writes, ``load_toml`` reads back as it was given —
arrays of tables (``[[loss]]``) and keys that are not bare words (a scenario spec) too."""

from __future__ import annotations

from pathlib import Path

import pytest

from openconvoy.core.config import dumps_toml, load_toml
from openconvoy.core.errors import ConfigError


def test_tables_arrays_of_tables_and_quoted_keys_round_trip(tmp_path: Path):
    data = {
        "leaderboard": {"name": "x", "seeds": [0, 1], "duration_s": 4.0, "on": True},
        "scenario": {"track-file:a/b.json": {"policy": {"speed_limit_mps": 40.0}}},
        "loss": [{"name": "per", "pers": [0.0, 0.5]}, {"name": "bursts", "pers": [0.3]}],
    }
    text = dumps_toml(data)
    assert "[[loss]]" in text and '[scenario."track-file:a/b.json".policy]' in text
    (tmp_path / "t.toml").write_text(text)
    assert load_toml(tmp_path / "t.toml") == data


def test_what_toml_cannot_hold_is_one_error():
    with pytest.raises(ConfigError, match="cannot write NoneType"):
        dumps_toml({"a": None})
