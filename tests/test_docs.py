"""The documentation's generated tables (docs/hooks/generated.py) against the code: every
value of the observation layout is described once, every description is of a real feature,
and the tables have one row per value, action component and config key."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import pytest

from openconvoy.convoy import ChannelConfig, ConvoyConfig, SafetyConfig, V2VConfig
from openconvoy.core import observation as ob
from openconvoy.core.observation import ObservationLayout
from openconvoy.envs.reward import RewardConfig

HOOK = Path(__file__).resolve().parents[1] / "docs" / "hooks" / "generated.py"


@pytest.fixture(scope="module")
def hook():
    spec = importlib.util.spec_from_file_location("docs_generated", HOOK)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rows(table: str) -> list[list[str]]:
    """The body rows of the markdown tables in ``table`` (headers left out)."""
    lines = table.splitlines()
    return [
        [c.strip() for c in ln.strip("|").split("|")]
        for i, ln in enumerate(lines)
        if ln.startswith("| ") and not (i + 1 < len(lines) and lines[i + 1].startswith("|---"))
    ]


def test_every_feature_is_described_and_every_description_is_a_feature(hook) -> None:
    features = (
        {("state", f) for f in ob.STATE_FEATURES}
        | {("own", f) for f in ob.OWN_FEATURES}
        | {("derived", f) for f in ob.DERIVED_FEATURES}
        | {("path", f) for f in ob.PATH_FEATURES}
    )
    assert set(hook.FEATURE_DOCS) == features


@pytest.mark.parametrize("M,k", [(1, 1), (2, 3), (4, 2)])
def test_the_index_covers_each_value_of_any_layout_once(hook, M: int, k: int) -> None:
    layout = ObservationLayout(M=M, k=k)
    rows = hook._layout_rows(layout)
    assert [r[0] for r in rows] == list(range(layout.size))
    for idx, slot, feature, block in rows:  # each row names the value the named view reads
        obs = layout.zeros()
        obs[idx] = 1.0
        view = layout.view(obs)
        if block == "state":
            name, j = slot[:-3], int(slot[-2])
            assert view.states(name)[j][ob.STATE_FEATURES.index(feature)] == 1.0
        elif block == "own":
            assert view.own[feature] == 1.0
        elif block == "derived":
            assert view.target(slot.removesuffix(" (target)"))[feature] == 1.0
        else:
            assert view.path[feature] == 1.0


def test_the_default_index_table_has_a_row_per_value_with_the_space_bounds(hook) -> None:
    rows = _rows(hook.observation_index())
    layout = ObservationLayout()
    assert [int(r[0]) for r in rows] == list(range(layout.size)) and layout.size == 111
    ages = [r for r in rows if r[2] == "`age`"]
    assert len(ages) == 4 * 3 and all(r[3:] == ["0", "10"] for r in ages)


def test_action_reward_and_convoy_file_tables_follow_the_code(hook) -> None:
    action = _rows(hook.action())
    assert [r[0] for r in action] == ["`paper`", "`track`", "`emergency-braking`"]
    assert action[0][3] == "0 … 5" and action[0][4] == "−π/2 … π/2"
    assert action[2][3] == "0 … 40"  # full-size cars
    reward = _rows(hook.reward())
    assert [r[0].strip("`") for r in reward] == [f.name for f in dataclasses.fields(RewardConfig)]
    convoy = _rows(hook.convoy_file())
    keys = [r[0].strip("`") for r in convoy]
    expected = [
        f.name
        for cls in (ConvoyConfig, V2VConfig, SafetyConfig, ChannelConfig)
        for f in dataclasses.fields(cls)
        if f.name not in ("v2v", "safety", "channel")
    ]
    assert keys == expected
    port = next(r for r in convoy if r[0] == "`port`")
    assert port[2:4] == ["`4200`", "an integer in [1, 65535]"]


def test_a_marker_is_replaced_and_an_unknown_one_fails_the_build(hook) -> None:
    page = "Infos: <!-- generated: info-keys -->.\n\n    <!-- generated: reward -->\n"
    out = hook.on_page_markdown(page)
    assert "`t_s`" in out.splitlines()[0]
    assert "    | `w_spacing` | 1.0 |" in out
    with pytest.raises(ValueError, match="unknown generated table 'nope'"):
        hook.on_page_markdown("<!-- generated: nope -->")
