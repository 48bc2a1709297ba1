"""``openconvoy experiment leaderboard``: a small leaderboard (seconds) whose table holds
every (scenario, condition, PER, policy) with the mean over seeds and its 95 % interval,
each condition applied as written, resumed without rerunning; its file round-trips."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.core.spacing import HIGHWAY_SPACING, SpacingConfig
from openconvoy.experiments.executor import ExecutorConfig
from openconvoy.experiments.leaderboard import (
    KEYS,
    LeaderboardConfig,
    interval,
    run_leaderboard,
    same_cells,
    table_markdown,
    with_overrides,
)
from openconvoy.experiments.runs import RunConfig, run_sim

T_975_2 = 4.302652729696143
"""Student's t, 97.5th percentile, 2 degrees of freedom (4.303 in any t table)."""

SMALL = """
[leaderboard]
name = "small"
policies = ["paper", "paper-mpc"]
scenarios = ["paper"]
seeds = 3
duration_s = 4.0

[[loss]]
name = "per"
pers = [0.0, 0.5]

[[loss]]
name = "bursts"
model = "gilbert-elliott"
mean_burst_s = 1.0
pers = [0.5]

[[loss]]
name = "latency-100ms"
latency_s = 0.1
pers = [0.0]
"""


def test_interval_is_students_t_on_the_sample_std():
    # t(0.975, 2) = 4.303 (any t table); s = 1 for 1, 2, 3: half width 4.303 / sqrt(3)
    got = interval([1.0, 2.0, 3.0])
    assert got["mean"] == 2.0 and got["n"] == 3
    assert got["hi"] - 2.0 == pytest.approx(T_975_2 / math.sqrt(3), rel=1e-9)
    assert got["lo"] == pytest.approx(2.0 - (got["hi"] - 2.0))
    assert interval([5.0, math.nan, 5.0]) == {"mean": 5.0, "lo": 5.0, "hi": 5.0, "n": 2}
    one = interval([1.5])
    assert one["mean"] == 1.5 and math.isnan(one["lo"]) and math.isnan(one["hi"])


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict]]:
    out = tmp_path_factory.mktemp("lb")
    (out / "small.toml").write_text(SMALL)
    config = LeaderboardConfig.from_toml(out / "small.toml")
    rows = run_leaderboard(
        config, out / "board", progress=False, executor=ExecutorConfig(jobs=1), run_logs=False
    )
    return out / "board", rows


def _runs(board: Path, cond: str, policy: str, per: float) -> list[dict]:
    base = board / "cells" / "paper" / cond / "runs" / policy / f"per_{per:.2f}"
    return [json.loads((base / f"seed_{s}" / "metrics.json").read_text()) for s in range(3)]


def test_the_table_has_every_cell_with_its_mean_and_95_percent_interval(small):
    board, rows = small
    cells = [(r["loss"], r["per"], r["policy"]) for r in rows]
    assert cells == [
        ("per", 0.0, "paper"), ("per", 0.0, "paper-mpc"),
        ("per", 0.5, "paper"), ("per", 0.5, "paper-mpc"),
        ("bursts", 0.5, "paper"), ("bursts", 0.5, "paper-mpc"),
        ("latency-100ms", 0.0, "paper"), ("latency-100ms", 0.0, "paper-mpc"),
    ]  # fmt: skip
    for r in rows:
        runs = _runs(board, r["loss"], r["policy"], r["per"])
        assert r["runs"] == 3 and r["scenario"] == "paper"
        assert r["runs_with_collision"] == sum(m["collisions"] > 0 for m in runs) == 0
        for key in KEYS:
            v = np.array([m[key] for m in runs], dtype=float)
            half = T_975_2 * v.std(ddof=1) / math.sqrt(3)
            assert r[key]["mean"] == pytest.approx(v.mean(), abs=1e-12)
            assert r[key]["hi"] - r[key]["mean"] == pytest.approx(half, rel=1e-9, abs=1e-12)
            assert r[key]["lo"] <= r[key]["mean"] <= r[key]["hi"]
    by = {(r["loss"], r["per"], r["policy"]): r for r in rows}
    err = "p95_platooning_error_m"
    # No loss, no noise: every seed is the same run, a zero-width interval; under loss not.
    assert by[("per", 0.0, "paper-mpc")][err]["lo"] == by[("per", 0.0, "paper-mpc")][err]["hi"]
    assert by[("per", 0.5, "paper")][err]["hi"] > by[("per", 0.5, "paper")][err]["lo"]
    # The conditions are applied: bursts are not independent loss, 100 ms is not none.
    for policy in ("paper", "paper-mpc"):
        assert by[("bursts", 0.5, policy)][err] != by[("per", 0.5, policy)][err]
        assert by[("latency-100ms", 0.0, policy)][err] != by[("per", 0.0, policy)][err]
    # MPC with plans beats the paper's PD here as on the full leaderboard (docs/leaderboard.md)
    assert by[("per", 0.0, "paper-mpc")][err]["mean"] < by[("per", 0.0, "paper")][err]["mean"]


def test_csv_markdown_and_plot_hold_the_same_table(small):
    board, rows = small
    with (board / "leaderboard.csv").open() as f:
        table = list(csv.DictReader(f))
    assert len(table) == len(rows)
    for line, r in zip(table, rows):
        assert (line["loss"], float(line["per"]), line["policy"]) == (
            r["loss"],
            r["per"],
            r["policy"],
        )
        for key in KEYS:
            for stat in ("mean", "lo", "hi"):
                assert float(line[f"{key}_{stat}"]) == pytest.approx(
                    r[key][stat], rel=1e-5, abs=1e-9
                )
    md = (board / "leaderboard.md").read_text()
    assert md == table_markdown(rows)
    r = rows[2]
    e = r["p95_platooning_error_m"]
    assert (
        f"| paper | per | 0.5 | `paper` | 3 | {e['mean']:.3g} [{e['lo']:.3g}, {e['hi']:.3g}] |"
        in md
    )
    assert (board / "leaderboard.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_finished_leaderboard_is_read_not_rerun(small, tmp_path: Path):
    board, rows = small
    probe = board / "cells" / "paper" / "per" / "runs" / "paper-mpc" / "per_0.50" / "seed_1"
    before = (probe / "metrics.json").stat().st_mtime_ns
    csv_before = (board / "leaderboard.csv").read_text()
    code = main(["experiment", "leaderboard", "--resume", str(board), "--quiet", "--no-plots"])
    assert code == 0
    assert (probe / "metrics.json").stat().st_mtime_ns == before
    assert (board / "leaderboard.csv").read_text() == csv_before


def test_the_file_round_trips_and_scenario_settings_reach_the_policies(tmp_path: Path):
    path = tmp_path / "lb.toml"
    path.write_text(
        SMALL.replace('scenarios = ["paper"]', 'scenarios = ["paper", "emergency-braking"]')
        + "\n[scenario.emergency-braking.policy]\nspeed_limit_mps = 40.0\n"
    )
    config = LeaderboardConfig.from_toml(path)
    again = tmp_path / "again.toml"
    again.write_text(config.to_toml())
    assert LeaderboardConfig.from_toml(again) == config
    experiment, labels = config.cell("emergency-braking", config.loss[0])
    assert labels == {
        "paper-emergency-braking": "paper",
        "paper-mpc-emergency-braking": "paper-mpc",
    }
    assert experiment.policy["paper-mpc-emergency-braking"] == {
        "base": "paper-mpc",
        "speed_limit_mps": 40.0,
    }
    plain, same = config.cell("paper", config.loss[1])
    assert same == {"paper": "paper", "paper-mpc": "paper-mpc"}
    assert plain.loss.model == "gilbert-elliott" and plain.pers == (0.5,)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[leaderboard]\npolicies = []\n", "policies must be given"),
        ('[leaderboard]\npolicies = ["paper"]\nbogus = 1\n', "bogus"),
        (
            '[leaderboard]\npolicies = ["paper"]\n[[loss]]\nname = "a b"\npers = [0.1]\n',
            "plain word",
        ),
        ('[leaderboard]\npolicies = ["paper"]\n[[loss]]\nname = "x"\npers = [1.5]\n', "pers"),
        (
            '[leaderboard]\npolicies = ["paper"]\n[[loss]]\nname = "x"\nmodel = "foo"\npers = [0.1]\n',
            "foo",
        ),
    ],
)
def test_a_bad_leaderboard_file_is_one_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code = main(["experiment", "leaderboard", "--config", str(path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "o" / "cells").exists()


def test_another_leaderboard_in_the_directory_is_refused(small, tmp_path: Path, capsys):
    board, _ = small
    other = tmp_path / "other.toml"
    other.write_text(SMALL.replace("seeds = 3", "seeds = 2"))
    code = main(["experiment", "leaderboard", "--config", str(other), "--out", str(board)])
    assert code == 2 and "holds another leaderboard" in capsys.readouterr().err


def test_the_shipped_leaderboard_is_the_issues_grid():
    """``examples/leaderboard.toml`` (docs/leaderboard.md): the four scenarios, PER 0-0.8,
    bursts, 100 ms latency, 10 seeds; MPC with plans and state-only beside the PD."""
    path = Path(__file__).resolve().parents[2] / "openconvoy/experiments/examples/leaderboard.toml"
    config = LeaderboardConfig.from_toml(path)
    assert config.scenarios == ("paper", "track", "emergency-braking", "highway-cut-in")
    assert config.policies == ("paper", "paper-tuned", "paper-mpc", "paper-mpc-state")
    assert config.seed_values == tuple(range(10))
    loss = {c.name: c for c in config.loss}
    assert loss["per"].pers == (0.0, 0.2, 0.4, 0.6, 0.8) and loss["per"].model == "bernoulli"
    assert loss["bursts"].model == "gilbert-elliott" and loss["bursts"].mean_burst_s == 1.0
    assert loss["latency-100ms"].latency_s == 0.1
    experiment, labels = config.cell("highway-cut-in", loss["per"])
    assert experiment.policy["paper-mpc-highway-cut-in"]["speed_limit_mps"] == 40.0
    assert sorted(labels.values()) == sorted(config.policies)
    # the highway scenarios run every policy with the highway spacing, the small-car
    # scenarios with the presets' own
    for scenario in ("emergency-braking", "highway-cut-in"):
        experiment, _ = config.cell(scenario, loss["per"])
        for table in experiment.policy.values():
            spacing = table["member"]["spacing"]
            assert SpacingConfig(**spacing) == HIGHWAY_SPACING
    assert config.cell("paper", loss["per"])[0].policy == {}


def _eb(tmp_path: Path, base: str, highway: bool) -> dict:
    """``base`` on ``emergency-braking`` at PER 0.4, seed 0, as the shipped leaderboard
    runs it (``highway``) or with the preset's 15 m."""
    extra = ""
    if highway:
        h = HIGHWAY_SPACING
        extra = (
            f'[policy.member.spacing]\nkind = "{h.kind}"\nstandstill_m = {h.standstill_m}\n'
            f"headway_s = {h.headway_s}\n"
        )
    path = tmp_path / f"{base}-{highway}.toml"
    path.write_text(f'[policy]\nbase = "{base}"\nspeed_limit_mps = 40.0\n{extra}')
    r = run_sim(RunConfig(scenario="emergency-braking", policy=str(path), per=0.4, seed=0))
    return {"metrics": r.metrics, "modes": set(np.asarray(r.log["mode"]).tolist())}


def test_the_highway_spacing_measures_control_not_an_emergency_stop(tmp_path: Path):
    """With the presets' 15 m at 25 m/s the braking rule stops the followers in the first
    second under loss and the leader drives away (p95 ~130 m); with the highway spacing
    they follow the leader's stop (docs/leaderboard.md)."""
    narrow = _eb(tmp_path, "paper-mpc", highway=False)
    wide = _eb(tmp_path, "paper-mpc", highway=True)
    assert "failsafe" in narrow["modes"] and narrow["metrics"]["p95_platooning_error_m"] > 50.0
    assert "failsafe" not in wide["modes"] and wide["metrics"]["p95_platooning_error_m"] < 5.0
    assert wide["metrics"]["collisions"] == 0


def test_part_of_a_leaderboard_then_more_shares_its_directory(tmp_path: Path):
    """``--scenarios paper`` first, then ``paper,emergency-braking`` in the same directory
    (the first part's cells read, not rerun); other seeds or settings are another board."""
    path = Path(__file__).resolve().parents[2] / "openconvoy/experiments/examples/leaderboard.toml"
    full = LeaderboardConfig.from_toml(path)
    first = with_overrides(full, scenarios=("paper",))
    more = with_overrides(full, scenarios=("paper", "emergency-braking"))
    assert first.scenario == {} and "emergency-braking" in more.scenario
    assert same_cells(first, more) and same_cells(more, first) and same_cells(more, full)
    assert not same_cells(first, with_overrides(more, seeds=(0, 1)))
    faster = dict(more.scenario, **{"emergency-braking": {"policy": {"speed_limit_mps": 30.0}}})
    assert not same_cells(full, with_overrides(more, scenario=faster))
    assert same_cells(first, with_overrides(more, scenario=faster))  # it shares only paper


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--config", "x.toml"], "needs --config FILE and --out DIR"),
        (["--resume", "nowhere"], "holds no leaderboard"),
        (["--resume", "nowhere", "--seeds", "2"], "as it was started"),
    ],
)
def test_leaderboard_flags_that_cannot_work_are_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], args: list[str], message: str
):
    assert main(["experiment", "leaderboard", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
