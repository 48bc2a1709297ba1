"""Tuning: the search improves on its base, the objective's numbers, and the written
policy file is what ``--policy`` accepts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.policies import load_policy
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy
from openconvoy.policies.presets import PRESETS
from openconvoy.policies.spec import classical_config
from openconvoy.train.tune import (
    TuneConfig,
    applicable,
    objective_of,
    tune,
    with_values,
    write_tuned,
)


def test_search_beats_its_base_on_a_known_objective() -> None:
    """A stand-in evaluator with its optimum at kp 0.8, kd 0.5, gain 0.6."""

    def evaluate(c: ClassicalConfig) -> float:
        return (c.speed.kp - 0.8) ** 2 + (c.speed.kd - 0.5) ** 2 + (c.heading.gain - 0.6) ** 2

    result = tune(TuneConfig(trials=40, seed=1), evaluate=evaluate)
    assert result.base_value == pytest.approx(evaluate(PRESETS["paper"]))
    assert result.best_value < 0.15 < result.base_value / 4  # base: 0.77
    assert result.best_params.keys() == {"speed.kp", "speed.kd", "heading.gain"}
    assert abs(result.best.speed.kp - 0.8) < 0.4
    # The first trial is the base itself, so the study never ends worse than it started.
    assert result.history[0]["speed.kp"] == pytest.approx(0.3)
    # Everything but the tuned values is the base's.
    assert result.best.member == PRESETS["paper"].member
    assert result.best.control_rate_hz == PRESETS["paper"].control_rate_hz


def test_same_seed_same_study() -> None:
    def evaluate(c: ClassicalConfig) -> float:
        return abs(c.speed.kp - 1.0) + abs(c.heading.gain - 0.3)

    a = tune(TuneConfig(trials=8, seed=3), evaluate=evaluate)
    b = tune(TuneConfig(trials=8, seed=3), evaluate=evaluate)
    assert a.history == b.history


def test_parameters_follow_the_policy_kind() -> None:
    assert applicable(PRESETS["paper"]) == ["speed.kp", "speed.kd", "heading.gain"]
    cacc = applicable(PRESETS["cacc-allpred"])
    assert "member.spacing.headway_s" in cacc and "member.spacing.standstill_m" in cacc
    changed = with_values(
        PRESETS["cacc-allpred"], {"member.spacing.headway_s": 1.2, "speed.kp": 0.9}, "x"
    )
    assert (
        changed.member.spacing.headway_s == 1.2 and changed.speed.kp == 0.9 and changed.name == "x"
    )
    with pytest.raises(ValueError, match="unknown tuning parameter"):
        TuneConfig(params=("speed.kq",))


def test_objective_weighs_collisions_above_spacing() -> None:
    cfg = TuneConfig()
    clean = {"p95_platooning_error_m": 0.5, "collisions": 0, "mean_speed_difference_mps": 0.1}
    crash = {"p95_platooning_error_m": 0.1, "collisions": 1, "mean_speed_difference_mps": 0.1}
    assert objective_of([clean, clean], cfg) == pytest.approx(0.6)
    assert objective_of([clean, crash], cfg) == pytest.approx(0.3 + 50.0 + 0.1)
    assert objective_of([{**clean, "p95_platooning_error_m": None}], cfg) > 100


def test_tune_cli_writes_a_policy_that_sim_accepts(tmp_path: Path) -> None:
    """Real simulated runs (short), through the command line end to end."""
    out = tmp_path / "tuned.toml"
    code = main(
        [
            "tune",
            "--policy",
            "paper",
            "--trials",
            "2",
            "--per",
            "0.3",
            "--seeds",
            "0",
            "--duration",
            "6",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    tuned = classical_config(str(out))
    assert tuned.name == "tuned" and tuned.member == PRESETS["paper"].member
    assert tuned.description.startswith(
        "paper tuned by openconvoy tune (2 trials, PER 0.3, 1 seeds): speed.kp"
    )
    summary = json.loads(out.with_suffix(".json").read_text())
    assert len(summary["trials"]) == 2 and summary["best_value"] <= summary["base_value"] + 1e-12
    assert isinstance(load_policy(str(out)), ClassicalPolicy)
    sim = tmp_path / "sim"
    assert (
        main(
            [
                "sim",
                "--policy",
                str(out),
                "--duration",
                "5",
                "--out",
                str(sim),
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )
    assert json.loads((sim / "metrics.json").read_text())["collisions"] == 0


def test_tuned_file_must_be_toml(tmp_path: Path) -> None:
    result = tune(TuneConfig(trials=1), evaluate=lambda c: 1.0)
    with pytest.raises(ValueError, match=r"\.toml"):
        write_tuned(result, tmp_path / "tuned.yaml")


def test_a_stored_study_resumes_without_repeating_finished_trials(tmp_path: Path) -> None:
    """Journal storage; a trial left running (its driver stopped) is evaluated again once."""
    import optuna
    from optuna.trial import TrialState

    from openconvoy.train.tune import open_storage

    evaluated: list[float] = []

    def evaluate(c: ClassicalConfig) -> float:
        evaluated.append(c.speed.kp)
        return (c.speed.kp - 0.8) ** 2 + (c.heading.gain - 0.6) ** 2

    journal = str(tmp_path / "study.journal")
    first = tune(TuneConfig(trials=4, seed=2), evaluate=evaluate, storage=journal, study_name="s")
    assert len(evaluated) == 5 and first.evaluated == 4  # the base, then 4 trials
    # A driver stopped mid-trial leaves it RUNNING in the storage.
    study = optuna.load_study(study_name="s", storage=open_storage(journal))
    orphan = study.ask()
    orphan_kp = orphan.suggest_float("speed.kp", 0.05, 5.0, log=True)
    for p in ("speed.kd", "heading.gain"):
        orphan.suggest_float(p, *((0.1, 5.0) if p == "speed.kd" else (0.05, 2.0)), log=True)
    evaluated.clear()
    second = tune(TuneConfig(trials=7, seed=2), evaluate=evaluate, storage=journal, study_name="s")
    # Only the three missing trials ran (the orphan's parameters first), not the base again.
    assert len(evaluated) == 3 and evaluated[0] == orphan_kp
    assert (second.evaluated, second.requeued, second.base_value) == (3, 1, first.base_value)
    assert second.history[:4] == first.history
    assert len(second.history) == 7 and len({h["speed.kp"] for h in second.history}) == 7
    states = [
        t.state for t in optuna.load_study(study_name="s", storage=open_storage(journal)).trials
    ]
    assert states.count(TrialState.FAIL) == 1 and states.count(TrialState.COMPLETE) == 7
    evaluated.clear()
    assert (
        tune(
            TuneConfig(trials=7, seed=2), evaluate=evaluate, storage=journal, study_name="s"
        ).evaluated
        == 0
    )
    assert evaluated == []
    with pytest.raises(ValueError, match=r"study 's' was made with other settings \(pers\)"):
        tune(TuneConfig(trials=8, pers=(0.5,)), evaluate=evaluate, storage=journal, study_name="s")


def test_tune_cli_storage_flags(tmp_path: Path, capsys) -> None:
    assert main(["tune", "--study-name", "x", "--out", str(tmp_path / "t.toml")]) == 2
    assert "--study-name needs --storage" in capsys.readouterr().err


def test_a_trial_stopped_before_its_parameters_were_drawn_is_failed_not_requeued(
    tmp_path: Path,
) -> None:
    """A driver killed between ``ask`` and its last ``suggest`` never evaluated that trial:
    the resumed study fails it and draws afresh (a partial candidate is no candidate)."""
    import optuna
    from optuna.trial import TrialState

    from openconvoy.train.tune import open_storage

    journal = str(tmp_path / "study.journal")
    evaluate = lambda c: (c.speed.kp - 0.8) ** 2  # noqa: E731
    tune(TuneConfig(trials=2, seed=3), evaluate=evaluate, storage=journal, study_name="s")
    study = optuna.load_study(study_name="s", storage=open_storage(journal))
    partial = study.ask()
    partial.suggest_float("speed.kp", 0.05, 5.0, log=True)
    second = tune(TuneConfig(trials=4, seed=3), evaluate=evaluate, storage=journal, study_name="s")
    assert (second.evaluated, second.requeued) == (2, 0)
    trials = optuna.load_study(study_name="s", storage=open_storage(journal)).trials
    assert trials[partial.number].state == TrialState.FAIL
    assert not any(t.user_attrs.get("requeued_from") is not None for t in trials)
