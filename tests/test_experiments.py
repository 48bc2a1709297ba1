"""Experiments (issue 3): sweeps, experiment files, presets, the ladder, compare."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.core.member import ConvoyMember
from openconvoy.core.state import VehicleState
from openconvoy.experiments import RunConfig, run_sim
from openconvoy.experiments.figures import SWEEP_FIGURES
from openconvoy.experiments.runs import ConvoySection, build_env
from openconvoy.experiments.sweep import ExperimentConfig, read_summary, run_experiment
from openconvoy.policies.presets import PRESETS
from openconvoy.policies.table1 import ROWS

EXAMPLES = Path(__file__).resolve().parents[1] / "openconvoy" / "experiments" / "examples"


def _mean(rows, policy, per, key):
    return next(r for r in rows if r["policy"] == policy and r["per"] == per)[key]["mean"]


# --- the paper's sweep -------------------------------------------------------------------


@pytest.mark.e2e
def test_paper_per_sweep_shows_the_papers_trend(tmp_path: Path, capsys):
    out = tmp_path / "sweep"
    rc = main(
        [
            "experiment",
            "per-sweep",
            "--policy",
            "paper",
            "--seeds",
            "3",
            "--out",
            str(out),
            "--quiet",
            "--jobs",
            "2",
        ]
    )
    assert rc == 0
    rows = json.loads((out / "summary.json").read_text())["rows"]
    assert [r["per"] for r in rows] == [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    assert all(r["runs"] == 3 for r in rows)
    for key in ("p95_platooning_error_m", "mean_speed_difference_mps"):
        assert _mean(rows, "paper", 0.6, key) > _mean(rows, "paper", 0.0, key), key
        assert set(rows[0][key]) == {"mean", "std", "min", "max"}
    # Loss is really applied: the measured delivery ratio tracks 1 - PER.
    for r in rows:
        assert r["delivery_ratio"]["mean"] == pytest.approx(1.0 - r["per"], abs=0.03)
        assert r["collisions"]["max"] == 0
    for name in SWEEP_FIGURES:
        assert (out / name).stat().st_size > 10_000, name
    assert len(list((out / "runs" / "paper").glob("per_*/seed_*/log.csv"))) == 21
    header = (out / "summary.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["policy", "per", "runs", "p95_platooning_error_m_mean"]
    assert "0.60" in capsys.readouterr().out


def test_rerun_from_the_copied_experiment_file_is_byte_identical(tmp_path: Path):
    fast = tmp_path / "elsewhere" / "fast.toml"
    fast.parent.mkdir()
    fast.write_text('[policy]\nbase = "paper"\nspeed = { kind = "pd", kp = 0.5, kd = 1.1 }\n')
    exp = tmp_path / "exp.toml"
    exp.write_text(
        '[experiment]\nname = "rerun"\nscenario = "paper"\n'
        f'policies = ["slow", "slow+ladder", "{fast}+ladder"]\n'
        "pers = [0.0, 0.5]\nseeds = 2\nduration_s = 8.0\n"
        '[loss]\nmodel = "gilbert-elliott"\nmean_burst_s = 0.5\n'
        '[policy.slow]\nbase = "paper"\nspeed_limit_mps = 3.0\n'
    )
    first = tmp_path / "first"
    assert (
        main(
            [
                "experiment",
                "per-sweep",
                "--config",
                str(exp),
                "--out",
                str(first),
                "--jobs",
                "2",
                "--no-plots",
            ]
        )
        == 0
    )
    manifest = json.loads((first / "manifest.json").read_text())
    from openconvoy import __version__

    assert manifest["openconvoy_version"] == __version__
    assert (first / "policies" / "slow.toml").is_file()
    # The policy file is inlined: the copy stands alone.
    fast.unlink()
    assert "[policy.fast]" in (first / "experiment.toml").read_text()
    second = tmp_path / "second"
    assert (
        main(
            [
                "experiment",
                "per-sweep",
                "--config",
                str(first / "experiment.toml"),
                "--out",
                str(second),
                "--quiet",
                "--jobs",
                "1",
                "--no-plots",
            ]
        )
        == 0
    )
    assert (first / "summary.csv").read_bytes() == (second / "summary.csv").read_bytes()
    assert (first / "experiment.toml").read_bytes() == (second / "experiment.toml").read_bytes()
    rows = read_summary(first)
    assert [(r["policy"], r["per"]) for r in rows] == [
        ("slow", 0.0),
        ("slow", 0.5),
        ("slow+ladder", 0.0),
        ("slow+ladder", 0.5),
        ("fast+ladder", 0.0),
        ("fast+ladder", 0.5),
    ]
    assert _mean(rows, "fast+ladder", 0.5, "p95_platooning_error_m") != _mean(
        rows, "slow+ladder", 0.5, "p95_platooning_error_m"
    )
    # A different seed set changes the numbers: the identity above is not vacuous.
    third = tmp_path / "third"
    assert (
        main(
            [
                "experiment",
                "per-sweep",
                "--config",
                str(first / "experiment.toml"),
                "--seeds",
                "1",
                "--out",
                str(third),
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )
    assert (first / "summary.csv").read_bytes() != (third / "summary.csv").read_bytes()


def test_experiment_files_are_strict_and_round_trip(tmp_path: Path):
    cfg = ExperimentConfig.from_toml(EXAMPLES / "emergency-braking-ladder.toml")
    assert cfg.loss.model == "gilbert-elliott" and cfg.seeds == (0, 1, 2, 3, 4)
    again = tmp_path / "again.toml"
    again.write_text(cfg.to_toml())
    assert ExperimentConfig.from_toml(again) == cfg
    assert ExperimentConfig.from_toml(EXAMPLES / "paper-per-sweep.toml").policies == (
        "paper",
        "paper+ladder",
    )
    bad = tmp_path / "bad.toml"
    bad.write_text('[experiment]\nscenario = "paper"\nper = [0.1]\n')
    with pytest.raises(ValueError, match="unknown key.*per"):
        ExperimentConfig.from_toml(bad)
    bad.write_text('[experiment]\n[loss]\nmodel = "markov"\n')
    with pytest.raises(ValueError, match="markov"):
        ExperimentConfig.from_toml(bad)
    bad.write_text("[experiment]\npers = [0.0, 1.5]\n")
    with pytest.raises(ValueError, match=r"pers\[1\].*1\.5.*\[0, 1\]"):
        ExperimentConfig.from_toml(bad)


def test_a_run_is_one_point_of_its_experiment_with_convoy_and_loss_nested():
    cfg = ExperimentConfig.from_toml(EXAMPLES / "emergency-braking-ladder.toml")
    label, run = cfg.run_configs()[-1]
    assert (run.convoy, run.loss) == (cfg.convoy, cfg.loss)
    assert (run.per, run.seed) == (cfg.pers[-1], cfg.seeds[-1])
    assert run.loss_config.per == run.per and run.loss_config.model == cfg.loss.model
    table = run.to_dict()
    assert table["loss"]["model"] == "gilbert-elliott" and "loss_model" not in table
    assert RunConfig.from_dict(table) == run
    with pytest.raises(ValueError, match=r"^run\.convoy\.ranging: expected true or false"):
        RunConfig.from_dict({"convoy": {"ranging": "yes"}})
    # a run table of the older flat form names where its key lives now
    with pytest.raises(ValueError, match=r"^run\.toml: loss_model: now loss\.model \("):
        RunConfig.from_dict({"per": 0.1, "loss_model": "bernoulli"}, "run.toml")
    with pytest.raises(ValueError, match="per must be in"):
        RunConfig(per=1.5)


# --- presets -----------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_platoons_the_paper_scenario_at_per_0(name: str):
    result = run_sim(RunConfig(scenario="paper", policy=name, per=0.0))
    m = result.metrics
    assert m["collisions"] == 0
    assert m["p95_platooning_error_m"] < 1.5
    assert m["duration_s"] == pytest.approx(60.0)  # not cut short
    # Measured against the preset's own desired gap: CACC presets ask far less than 15 m.
    desired = result.log["desired_gap_m"][result.log["vehicle_id"] > 0]
    if PRESETS[name].member.spacing.kind == "constant-distance":
        assert np.allclose(desired, 15.0)
    else:
        assert desired.max() < 6.0
        assert m["min_gap_m"] < 5.0


def _claimed(name: str) -> tuple[str, str]:
    """The topology and trigger a preset's name claims (``-pd``: the PD stand-in's alias)."""
    name = name.removesuffix("-pd")
    trigger = "event" if name.endswith("-event") else "periodic"
    for word, topology in (
        ("leader", "leader"),
        ("allpred", "all-predecessors"),
        ("paper", "all-predecessors"),
        ("lookahead1", "lookahead:1"),
        ("lookaheadN", "lookahead:N"),
        ("mcacc", "bidirectional"),
    ):
        if word in name:
            return topology, trigger
    raise AssertionError(f"no claim in {name}")


TABLE1_ROWS = {row().name for row in ROWS}

KEPT_BY_VEHICLE_2_OF_4 = {
    "leader": {0},
    "all-predecessors": {0, 1},
    "lookahead:1": {1},
    "lookahead:N": {0, 1},
    "bidirectional": {1, 3},
}


@pytest.mark.parametrize("name", [n for n in PRESETS if n not in TABLE1_ROWS])
def test_each_preset_uses_the_topology_and_trigger_it_claims(name: str):
    """(The Table I rows are named after their papers: ``tests/policies/test_mpc_policy.py``.)"""
    cfg = PRESETS[name].member
    topology, trigger = _claimed(name)
    assert (cfg.topology, cfg.trigger.kind) == (topology, trigger)
    member = ConvoyMember(2, 4, cfg)
    assert {j for j in (0, 1, 3) if member.rx.keeps(j)} == KEPT_BY_VEHICLE_2_OF_4[topology]
    # R^i also keeps the predecessor's messages, for the braking rule (issue 22, D47).
    kept = {
        j
        for j in (0, 1, 3)
        if member.receive(VehicleState(j, 0.0, 10.0 * (2 - j), 0.0, 1.0, 0.0), 0.0)
    }
    assert kept == KEPT_BY_VEHICLE_2_OF_4[topology] | {1}


def test_a_leader_following_member_shows_its_policy_the_leader_only():
    member = ConvoyMember(2, 3, PRESETS["platoon-leader"].member)
    assert member.receive(VehicleState(1, 0.0, 15.0, 0.0, 1.0, 0.0), 0.0)  # for the rule
    assert member.receive(VehicleState(0, 0.0, 30.0, 0.0, 1.0, 0.0), 0.0)
    member.observe_own(VehicleState(2, 0.0, 0.0, 0.0, 1.0, 0.0))
    view = member.layout.view(member.sense(0.0).observation)
    assert view.states("pred_1")[0, 6] == 0.0 and view.states("pred_2")[0, 6] == 1.0
    assert member.gap_estimate(0.0) == (15.0, 0.0)


@pytest.mark.parametrize("periodic", [n for n in PRESETS if n + "-event" in PRESETS])
def test_event_triggered_members_send_less_on_a_steady_road(periodic: str):
    # The paper scenario's first phase: a steady 1 m/s on a straight road.
    sent = {}
    for name in (periodic, periodic + "-event"):
        log = run_sim(RunConfig(policy=name, duration_s=15.0)).log
        sent[name] = [int(log["msgs_sent"][log["vehicle_id"] == v].max()) for v in (0, 1, 2)]
    for v in range(3):
        assert sent[periodic + "-event"][v] < 0.5 * sent[periodic][v], (v, sent)
    assert sent[periodic][0] == 151  # 15 s at one message per 0.1 s, t = 0 included


# --- degradation: ladder and ranging -----------------------------------------------------


def test_ranging_option_gives_followers_a_sensor():
    env, policies = build_env(
        RunConfig(
            scenario="emergency-braking",
            convoy=ConvoySection(ranging=True, ranging_max_range_m=150.0),
        )
    )
    assert env.presets[0].ranging is None
    assert [p.ranging.max_range_m for p in env.presets[1:]] == [150.0, 150.0]
    assert set(policies) == set(env.possible_agents)
    env, _ = build_env(RunConfig())
    assert all(p.ranging is None for p in env.presets)


@pytest.mark.e2e
def test_emergency_braking_under_bursts_the_ladder_prevents_collisions(tmp_path: Path):
    cfg = ExperimentConfig.from_toml(EXAMPLES / "emergency-braking-ladder.toml")
    assert cfg.pers == (0.6,) and cfg.loss.mean_burst_s == 1.0 and len(cfg.seeds) == 5
    result = run_experiment(cfg, tmp_path / "eb", jobs=2, progress=False)
    by = {label: [m for lab, _, m in result.runs if lab == label] for label in cfg.policies}
    without, with_ladder = by["cacc-highway"], by["cacc-highway+ladder"]
    assert all(m["collisions"] == 0 for m in with_ladder)
    # Without the ladder CACC once collided here; since stale targets only slow it (issue
    # 10: bounded, braking dead-reckoning; the nearest predecessor caps σ) it no longer
    # does, but it still ends closer than with the ladder.
    assert all(m["collisions"] == 0 for m in without)
    mean = lambda runs: float(np.mean([m["min_gap_m"] for m in runs]))  # noqa: E731
    assert mean(with_ladder) > mean(without)
    assert min(m["min_gap_m"] for m in with_ladder) > max(4.8, min(m["min_gap_m"] for m in without))
    # Loss really was bursty at about PER 0.6.
    assert 0.25 < np.mean([m["delivery_ratio"] for m in without]) < 0.55
    # Both policies in one figure (min gap vs PER and closest gap over time).
    assert (tmp_path / "eb" / "fig9_min_gap_vs_per.png").stat().st_size > 10_000
    assert {r["policy"] for r in result.rows} == set(cfg.policies)
    assert set(result.series) == {(p, 0.6) for p in cfg.policies}


# --- compare -----------------------------------------------------------------------------


def test_compare_two_sweeps_matches_rows_by_per(tmp_path: Path, capsys):
    for label in ("paper", "paper+ladder"):
        assert (
            main(
                [
                    "experiment",
                    "per-sweep",
                    "--policy",
                    label,
                    "--pers",
                    "0,0.6",
                    "--seeds",
                    "1",
                    "--duration",
                    "6",
                    "--out",
                    str(tmp_path / label),
                    "--quiet",
                    "--no-plots",
                    "--jobs",
                    "1",
                ]
            )
            == 0
        )
    capsys.readouterr()
    out = tmp_path / "cmp.json"
    assert (
        main(
            ["compare", str(tmp_path / "paper"), str(tmp_path / "paper+ladder"), "--out", str(out)]
        )
        == 0
    )
    result = json.loads(out.read_text())
    assert [r["per"] for r in result["rows"]] == [0.0, 0.6]
    first = result["rows"][0]
    assert (first["policy_a"], first["policy_b"]) == ("paper", "paper+ladder")
    # At PER 0 the ladder never engages: identical numbers.
    assert first["p95_platooning_error_m"]["diff"] == 0.0
    assert "paper | paper+ladder" in capsys.readouterr().out
    d = result["rows"][1]["delivery_ratio"]
    assert not math.isnan(d["a"]) and d["a"] < 0.6


def test_compare_says_what_it_left_out(tmp_path: Path, capsys):
    """Rows one sweep has and the other lacks are named, not silently dropped."""
    argv = ["experiment", "per-sweep", "--seeds", "1", "--duration", "4", "--quiet"]
    argv += ["--no-plots", "--jobs", "1"]
    assert main([*argv, "--policy", "paper", "--pers", "0,0.3", "--out", str(tmp_path / "a")]) == 0
    two = ["--policy", "paper", "--policy", "paper+ladder", "--pers", "0.3,0.6"]
    assert main([*argv, *two, "--out", str(tmp_path / "b")]) == 0
    capsys.readouterr()
    out = tmp_path / "cmp.json"
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    result = json.loads(out.read_text())
    assert [(r["policy_a"], r["per"]) for r in result["rows"]] == [("paper", 0.3)]
    assert result["left_out"] == {
        "a": ["paper at PER 0.00"],
        "b": ["paper at PER 0.60", "paper+ladder at PER 0.30", "paper+ladder at PER 0.60"],
    }
    assert "left out, only in A (nothing to match in B): paper at PER 0.00" in printed
    assert (
        "left out, only in B (nothing to match in A): paper at PER 0.60, "
        "paper+ladder at PER 0.30, paper+ladder at PER 0.60"
    ) in printed
