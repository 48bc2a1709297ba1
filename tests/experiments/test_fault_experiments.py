"""Faults and authentication in experiment files and ``tune`` (``ExperimentConfig.faults``,
``.auth``; ``TuneConfig`` likewise): every run gets them, the run directory's copy keeps
them, and a bad spec or value is one error line from the CLI, nothing written."""

from __future__ import annotations

from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.core.errors import ConfigError
from openconvoy.experiments.sweep import ExperimentConfig, read_summary
from openconvoy.train.tune import TuneConfig, grid_runs

EXPERIMENT = (
    '[experiment]\nname = "f"\npolicies = ["paper"]\npers = [0.0, 0.3]\nseeds = 1\n'
    "duration_s = 12.0\n"
)


def test_every_run_of_an_experiment_gets_its_faults_and_auth(tmp_path: Path):
    exp = tmp_path / "e.toml"
    exp.write_text(EXPERIMENT + 'faults = ["halt:1@5.0", " forge:0@3"]\nauth = "off"\n')
    config = ExperimentConfig.from_toml(exp)
    assert config.faults == ("halt:1@5", "forge:0@3") and config.auth == "off"  # normalized
    runs = [rc for _, rc in config.run_configs()]
    assert len(runs) == 2 and {(rc.faults, rc.auth) for rc in runs} == {(config.faults, "off")}
    assert ExperimentConfig().faults == () and ExperimentConfig().auth == "required"
    again = tmp_path / "again.toml"
    again.write_text(config.to_toml())
    assert ExperimentConfig.from_toml(again) == config


def test_the_run_directorys_copy_reruns_the_fault_sweep(tmp_path: Path, capsys):
    exp = tmp_path / "e.toml"
    exp.write_text(EXPERIMENT + 'faults = ["halt:1@4"]\n')
    sweep = ["experiment", "per-sweep", "--quiet", "--no-plots", "--jobs", "1", "--out"]
    assert main([*sweep, str(tmp_path / "a"), "--config", str(exp)]) == 0
    copy = tmp_path / "a" / "experiment.toml"
    assert 'faults = ["halt:1@4"]' in copy.read_text()
    assert 'auth = "required"' in copy.read_text()
    assert main([*sweep, str(tmp_path / "b"), "--config", str(copy)]) == 0
    assert (tmp_path / "a" / "summary.csv").read_bytes() == (
        tmp_path / "b" / "summary.csv"
    ).read_bytes()
    # --fault replaces the file's faults: a later halt is another sweep.
    assert main([*sweep, str(tmp_path / "c"), "--config", str(exp), "--fault", "halt:1@9"]) == 0
    assert 'faults = ["halt:1@9"]' in (tmp_path / "c" / "experiment.toml").read_text()
    early, late = read_summary(tmp_path / "a"), read_summary(tmp_path / "c")
    for e, la in zip(early, late):  # vehicle 1 stopped earlier: the leader got farther away
        assert e["p95_platooning_error_m"]["mean"] > la["p95_platooning_error_m"]["mean"] > 1.0


BAD = [
    ('faults = ["brake:1@3"]\n', [], "faults: bad fault 'brake:1@3': unknown fault kind"),
    ('faults = ["halt:1"]\n', [], "faults: bad fault 'halt:1': missing ':' or '@'"),
    ('faults = "halt:1@3"\n', [], "faults: expected a list of strings"),
    ('faults = ["halt:7@3"]\n', [], "fault halt:7@3: no vehicle 7 in a convoy of 3"),
    ('auth = "maybe"\n', [], "auth: must be 'required' or 'off', got 'maybe'"),
    ("", ["--fault", "halt:x@3"], "bad fault 'halt:x@3'"),
    ("", ["--fault", "forge:-1@3"], "fault vehicle must be an index >= 0"),
]


@pytest.mark.parametrize("extra, flags, words", BAD, ids=[b[2][:24] for b in BAD])
def test_a_bad_fault_or_auth_is_one_line_and_nothing_written(
    tmp_path: Path, capsys, extra: str, flags: list[str], words: str
):
    exp = tmp_path / "e.toml"
    exp.write_text(EXPERIMENT + extra)
    argv = ["experiment", "per-sweep", "--config", str(exp), "--out", str(tmp_path / "out")]
    assert main([*argv, "--quiet", *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("openconvoy: error: "), err
    assert words in err[0], err[0]
    assert not (tmp_path / "out").exists()


def test_tune_takes_faults_and_auth_for_every_grid_run():
    config = TuneConfig(pers=(0.0, 0.3), seeds=(5,), faults=("halt:1@30.0",), auth="off")
    runs = grid_runs(config, "paper")
    assert [(rc.per, rc.faults, rc.auth) for rc in runs] == [
        (0.0, ("halt:1@30",), "off"),
        (0.3, ("halt:1@30",), "off"),
    ]
    with pytest.raises(ConfigError, match="bad fault 'halt'"):
        TuneConfig(faults=("halt",))
    with pytest.raises(ConfigError, match="auth must be 'required' or 'off'"):
        TuneConfig(auth="none")


@pytest.mark.parametrize(
    "flags, words",
    [
        (["--fault", "stall:1@3"], "unknown fault kind 'stall'"),
        (["--fault", "halt:5@3"], "no vehicle 5 in a convoy of 3"),
        (["--auth", "none"], "argument --auth: invalid choice: 'none'"),
    ],
)
def test_a_bad_tune_fault_is_one_line(tmp_path: Path, capsys, flags: list[str], words: str):
    out = tmp_path / "t.toml"
    argv = ["tune", "--trials", "1", "--per", "0.0", "--duration", "2", "--no-progress"]
    assert main([*argv, "--out", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("openconvoy: error: ") and words in err[0], err
    assert not out.exists()


def test_a_stored_study_keeps_its_faults_and_older_studies_resume(tmp_path: Path):
    """Faults and auth define the objective: a study resumes only with the same ones; a
    study stored before they existed ran without faults and resumes so."""
    import optuna

    from openconvoy.train.tune import STUDY_ATTR, open_storage, tune

    def evaluate(c) -> float:
        return (c.speed.kp - 0.8) ** 2

    journal = str(tmp_path / "study.journal")
    tune(TuneConfig(trials=1, seed=3), evaluate=evaluate, storage=journal, study_name="s")
    study = optuna.load_study(study_name="s", storage=open_storage(journal))
    older = {k: v for k, v in study.user_attrs[STUDY_ATTR].items() if k not in ("faults", "auth")}
    study.set_user_attr(STUDY_ATTR, older)
    resumed = tune(TuneConfig(trials=2, seed=3), evaluate=evaluate, storage=journal, study_name="s")
    assert resumed.evaluated == 1
    braking = TuneConfig(trials=3, seed=3, faults=("halt:1@3",))
    with pytest.raises(ConfigError, match=r"made with other settings \(faults\)"):
        tune(braking, evaluate=evaluate, storage=journal, study_name="s")
    with pytest.raises(ConfigError, match=r"made with other settings \(auth\)"):
        tune(TuneConfig(trials=3, auth="off"), evaluate=evaluate, storage=journal, study_name="s")


def test_the_shipped_robustness_example_loads():
    examples = Path(__file__).resolve().parents[2] / "openconvoy" / "experiments" / "examples"
    config = ExperimentConfig.from_toml(examples / "braking-predecessor.toml")
    assert config.faults == ("halt:1@30",) and config.auth == "required"
    assert all(rc.faults == ("halt:1@30",) for _, rc in config.run_configs())
