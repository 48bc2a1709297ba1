"""The whole learned-policy path: a short training run, its files, ``sim`` and a deployed
vehicle running them, the export matching SB3's ``predict``, layout checks.

The runs are tiny (a few thousand steps): these tests check the plumbing and the numbers
that must hold for any trained network, not the quality of the follower.
"""

from __future__ import annotations

import copy
import json
import math
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.core.member import MemberConfig
from openconvoy.policies import load_policy
from openconvoy.policies.learned import load_learned, load_sb3_predict, read_zip_meta
from openconvoy.policies.presets import PRESETS
from openconvoy.train.config import TrainConfig, load_train_config
from openconvoy.train.export import export_policy, max_action_difference, sample_observations
from openconvoy.train.validate import validate

STEPS = 2048


FAST = (
    "checkpoint_every = 1024\nvalidation_pers = [0.3]\nvalidation_seeds = [1000]\n"
    "validation_duration_s = 4.0\n"
)
"""Tiny checkpoints and validation runs, so the tests see every file a run writes."""


@pytest.fixture(scope="module")
def ppo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("train")
    (tmp / "fast.toml").write_text(FAST)
    run = tmp / "run"
    code = main(
        [
            "train",
            "--config",
            str(tmp / "fast.toml"),
            "--steps",
            str(STEPS),
            "--out",
            str(run),
            "--envs",
            "2",
            "--seed",
            "3",
            "--per-range",
            "0.1",
            "0.4",
            "--no-progress",
        ]
    )
    assert code == 0
    return run


@pytest.fixture(scope="module")
def ppo_npz(ppo_run: Path) -> Path:
    out = ppo_run / "policy.npz"
    assert main(["export", str(ppo_run), "--out", str(out)]) == 0
    return out


def test_training_writes_a_complete_run_directory(ppo_run: Path) -> None:
    for name in (
        "config.toml",
        "policy.zip",
        "last.zip",
        "policy.json",
        "vecnormalize.pkl",
        "train.json",
        "validation.json",
    ):
        assert (ppo_run / name).is_file(), name
    assert list((ppo_run / "tb").rglob("events.out.tfevents.*")), "no TensorBoard events"
    assert sorted(p.name for p in (ppo_run / "checkpoints").iterdir()) == [
        "policy_1024_steps.zip",
        "policy_2048_steps.zip",
    ]
    # policy.zip is the best-validated of the checkpoints and the final network.
    validation = json.loads((ppo_run / "validation.json").read_text())
    objectives = [v["objective"] for v in validation["validations"]]
    assert len(objectives) == 3 and all(len(v["runs"]) == 1 for v in validation["validations"])
    best = validation["validations"][objectives.index(min(objectives))]
    assert validation["chosen"] == best["path"]
    assert (ppo_run / "policy.zip").read_bytes() == Path(best["path"]).read_bytes()
    summary = json.loads((ppo_run / "train.json").read_text())
    # SB3 rounds up to whole rollouts: 2 envs x 2 followers x n_steps 64 = 256 per rollout.
    assert summary["steps"] == 2048 and summary["n_slots"] == 4
    config = load_train_config(ppo_run / "config.toml")
    assert config.total_steps == STEPS and config.seed == 3 and config.n_envs == 2
    assert config.validation_seeds == (1000,) and config.checkpoint_every == 1024
    assert config.randomization.per_range == (0.1, 0.4)
    # What the policy records: layout, member config, rate, normalization, its residual base.
    meta = read_zip_meta(ppo_run / "policy.zip")
    assert meta.layout == PRESETS["paper"].member.layout.describe()
    assert meta.member_config == PRESETS["paper"].member
    assert meta.control_rate_hz == 20.0
    assert meta.base is not None and meta.base.speed == PRESETS["paper"].speed
    assert meta.obs_mean is not None and meta.obs_mean.shape == (meta.layout["size"],)
    assert np.all(meta.obs_var > 0)
    assert json.loads((ppo_run / "policy.json").read_text())["layout"] == meta.layout


def test_a_run_config_reproduces_the_run(ppo_run: Path, tmp_path: Path) -> None:
    """The same config.toml gives the same network (seeded end to end)."""
    again = tmp_path / "again"
    assert (
        main(
            [
                "train",
                "--config",
                str(ppo_run / "config.toml"),
                "--out",
                str(again),
                "--no-progress",
            ]
        )
        == 0
    )
    a, b = load_learned(ppo_run / "policy.zip"), load_learned(again / "policy.zip")
    np.testing.assert_array_equal(a.meta.obs_mean, b.meta.obs_mean)
    obs = sample_observations(a, n=50)
    np.testing.assert_array_equal([a.act(o) for o in obs], [b.act(o) for o in obs])


def test_export_matches_sb3_predict(ppo_run: Path, ppo_npz: Path, tmp_path: Path) -> None:
    """The .npz against SB3 itself, within 1e-5 in SI units: the final network (last.zip)
    exported and compared with VecNormalize's own normalization (vecnormalize.pkl, saved
    with it) and ``predict(deterministic=True)``; then the run's chosen policy.zip."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    last = PPO.load(str(ppo_run / "last.zip"), device="cpu")
    vecnorm = VecNormalize.load(str(ppo_run / "vecnormalize.pkl"), venv=_DummyVenv(last))
    npz_last = load_learned(export_policy(ppo_run / "last.zip", tmp_path / "last.npz"))
    obs = sample_observations(npz_last, n=300, per=0.5)
    rng = np.random.default_rng(0)
    # Also observations far from the training data (clipping paths).
    meta = npz_last.meta
    wide = meta.obs_mean + rng.normal(scale=3.0, size=(100, obs.shape[1])) * np.sqrt(meta.obs_var)
    obs = np.concatenate([obs, wide.astype(np.float32)])
    base = meta.make_base()
    worst = 0.0
    for o in obs:
        a, _ = last.predict(vecnorm.normalize_obs(o), deterministic=True)
        worst = max(worst, float(np.max(np.abs(npz_last.act(o) - meta.to_si(a, base.act(o))))))
    assert worst <= 1e-5
    # The exported network is not trivially constant: the actions vary with the input.
    assert np.ptp([npz_last.normalized_action(o)[0] for o in obs]) > 1e-3

    chosen = PPO.load(str(ppo_run / "policy.zip"), device="cpu")
    npz = load_learned(ppo_npz)
    # The .zip runs the export's numpy forward (equal to the bit); SB3's predict, the
    # reference `openconvoy export` checks against, is within 1e-5 of it.
    zipped = load_learned(ppo_run / "policy.zip")
    np.testing.assert_array_equal([zipped.act(o) for o in obs], [npz.act(o) for o in obs])
    reference = load_sb3_predict(ppo_run / "policy.zip")
    assert max_action_difference(reference, zipped, obs) <= 1e-5
    worst = max(
        float(
            np.max(
                np.abs(
                    npz.normalized_action(o)
                    - chosen.predict(npz.meta.normalize(o).astype(np.float32), deterministic=True)[
                        0
                    ]
                )
            )
        )
        for o in obs
    )
    assert worst <= 1e-5


def test_export_says_what_it_waits_for_and_checks_against_sb3(
    ppo_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    """A person at a terminal is told what the ~10 s are for; the check's line gives the
    largest action difference from SB3's own predict (the reference, not the .zip's
    numpy forward, which equals the export by construction)."""
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    out = tmp_path / "said.npz"
    assert main(["export", str(ppo_run), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert said.err.startswith(f"exporting {ppo_run / 'policy.zip'} to {out}, then checking it")
    assert "(loads torch: ~10 s)" in said.err
    m = re.fullmatch(
        rf"{re.escape(str(out))}: max \|action difference\| vs SB3 predict = (\S+) on 400 observations\n",
        said.out,
    )
    assert m is not None, said.out
    assert 0.0 <= float(m.group(1)) <= 1e-5


class _DummyVenv:
    """The spaces VecNormalize.load needs, without building environments."""

    def __init__(self, model) -> None:
        self.observation_space = model.observation_space
        self.action_space = model.action_space
        self.num_envs = 1
        self.render_mode = None

    def get_attr(self, name, indices=None):
        return [None]


def _worst_against_predict(npz, model, observations: np.ndarray) -> float:
    """Largest |normalized action| difference between an export and SB3's deterministic
    ``predict`` of its model on ``observations``."""
    return max(
        float(
            np.max(
                np.abs(
                    npz.normalized_action(o)
                    - model.predict(npz.meta.normalize(o).astype(np.float32), deterministic=True)[0]
                )
            )
        )
        for o in observations
    )


def _sweep_csv(policy: Path, out: Path, duration_s: float = 8.0) -> str:
    """A two-PER sweep of ``policy``: its summary.csv with the policy's label blanked (the
    one thing that names the artifact), every number as the sweep wrote it."""
    from openconvoy.experiments.sweep import ExperimentConfig, run_experiment

    config = ExperimentConfig(
        policies=(str(policy),), pers=(0.0, 0.3), seeds=1, duration_s=duration_s
    )
    run_experiment(config, out, jobs=1, progress=False, figures=False)
    text = (out / "summary.csv").read_text()
    assert text.count(str(policy)) == 2  # one row per PER
    return text.replace(str(policy), "POLICY")


def test_sac_export_matches_sb3_predict(tmp_path: Path) -> None:
    """SAC's actor (tanh-squashed mean) exports too, and the export sweeps as its .zip,
    byte for byte; the .zip's numpy forward is SB3's predict within 1e-5."""
    from stable_baselines3 import SAC

    run = tmp_path / "sac"
    cfg = tmp_path / "sac.toml"
    cfg.write_text(
        'algo = "sac"\ntotal_steps = 400\nn_envs = 1\ncheckpoint_every = 0\nvalidation_seeds = []\n'
        "[sac]\nlearning_starts = 100\nbatch_size = 32\nnet_arch = [32, 32]\n"
    )
    assert main(["train", "--config", str(cfg), "--out", str(run), "--no-progress"]) == 0
    npz = load_learned(export_policy(run, tmp_path / "sac.npz"))
    model = SAC.load(str(run / "policy.zip"), device="cpu")
    assert npz.meta.algo == "sac"
    obs = sample_observations(npz, n=200)
    assert _worst_against_predict(npz, model, obs) <= 1e-5
    assert _worst_against_predict(load_learned(run / "policy.zip"), model, obs) <= 1e-5
    zipped = _sweep_csv(run / "policy.zip", tmp_path / "sweep-zip", duration_s=4.0)
    assert zipped == _sweep_csv(tmp_path / "sac.npz", tmp_path / "sweep-npz", duration_s=4.0)


@pytest.mark.parametrize("artifact", ["policy.zip", "policy.npz"])
def test_sim_runs_the_trained_policy(
    ppo_run: Path, ppo_npz: Path, artifact: str, tmp_path: Path
) -> None:
    out = tmp_path / "sim"
    code = main(
        [
            "sim",
            "--policy",
            str(ppo_run / artifact),
            "--per",
            "0.3",
            "--duration",
            "8",
            "--out",
            str(out),
            "--quiet",
            "--no-plots",
        ]
    )
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["collisions"] == 0
    assert 0.0 <= metrics["p95_platooning_error_m"] < 5.0
    assert math.isclose(metrics["duration_s"], 8.0, abs_tol=0.06)


def test_zip_and_npz_drive_the_same_sim(ppo_run: Path, ppo_npz: Path, tmp_path: Path) -> None:
    from openconvoy.experiments.runs import RunConfig, run_sim

    runs = [
        run_sim(RunConfig(policy=str(ppo_run / f), per=0.3, seed=1, duration_s=6.0))
        for f in ("policy.zip", "policy.npz")
    ]
    # Both run the same numpy forward (the .zip's actor extracted on load): equal to the bit.
    for column in ("x_m", "y_m", "speed_mps", "cmd_speed_mps"):
        np.testing.assert_array_equal(runs[0].log[column], runs[1].log[column], err_msg=column)


def test_layout_mismatch_is_refused_for_a_trained_zip(ppo_run: Path) -> None:
    with pytest.raises(
        ValueError,
        match=r"policy.zip: policy was trained for another observation layout \(M 2 vs 1",
    ):
        load_learned(ppo_run / "policy.zip", member_config=MemberConfig(M=1))


def test_layout_choice_reaches_the_trained_policy(tmp_path: Path) -> None:
    """``--M``/``--k`` train for another layout; that policy records and enforces it."""
    run = tmp_path / "m3"
    cfg = tmp_path / "m3.toml"
    cfg.write_text("validation_seeds = []\n")
    assert (
        main(
            [
                "train",
                "--config",
                str(cfg),
                "--steps",
                "512",
                "--envs",
                "1",
                "--M",
                "3",
                "--k",
                "2",
                "--out",
                str(run),
                "--no-progress",
            ]
        )
        == 0
    )
    assert not (run / "last.zip").exists()  # no validation: policy.zip is the final network
    policy = load_policy(str(run / "policy.zip"))
    assert policy.meta.layout == {
        "version": 1,
        "M": 3,
        "k": 2,
        "size": MemberConfig(M=3, k=2).layout.size,
    }
    with pytest.raises(ValueError, match="M 3 vs 2"):
        load_learned(run / "policy.zip", member_config=PRESETS["paper"].member)


@pytest.mark.parametrize("artifact", ["policy.zip", "policy.npz"])
def test_deploy_runs_the_trained_policy_on_a_simulated_vehicle(
    ppo_run: Path, ppo_npz: Path, artifact: str, tmp_path: Path
) -> None:
    """A leader (paper scenario) and a follower driven by the trained file: real MAVLink
    to simulated vehicles, V2V on an in-process bus, the deploy runner's real-time loop."""
    from openconvoy.bridge.localv2v import LocalBus, LocalV2V
    from openconvoy.bridge.mavlink.link import MavlinkLink
    from openconvoy.bridge.runner import DeployRunner, RunnerOptions
    from openconvoy.comms.geodesy import Origin
    from openconvoy.convoy import ConvoyConfig
    from openconvoy.demo import sim_vehicle_configs, start_local_sim_vehicles
    from openconvoy.envs.scenarios import make_scenario
    from openconvoy.envs.vehicles import vehicle_preset

    names = ("1/10", "1/6")
    convoy = ConvoyConfig(name="learned", vehicles=names)
    origin = Origin(*convoy.origin)
    presets = [vehicle_preset(v) for v in names]
    scenario = make_scenario("paper", presets=presets)
    init = scenario.initial_state()
    policies = [load_policy("paper"), load_policy(str(ppo_run / artifact))]
    bus = LocalBus()
    vehicles, runners, results = [], [], {}
    try:
        configs = sim_vehicle_configs(init, origin, presets, ready_after_s=0.0)
        for i, (vehicle, url) in enumerate(start_local_sim_vehicles(configs)):
            vehicles.append(vehicle)
            link = MavlinkLink(
                url,
                origin,
                vehicle_id=i,
                length_m=presets[i].length_m,
                on_status=lambda line: None,
            )
            runners.append(
                DeployRunner(
                    RunnerOptions(
                        vehicle_id=i,
                        rate_hz=policies[i].control_rate_hz,
                        duration_s=4.0,
                        status_period_s=0.0,
                        connect_timeout_s=5.0,
                        arm_timeout_s=10.0,
                    ),
                    convoy,
                    policies[i],
                    link,
                    LocalV2V(bus),
                    leader=scenario if i == 0 else None,
                    lengths=[p.length_m for p in presets],
                    log_dir=tmp_path / "deploy",
                    on_status=lambda line: None,
                )
            )
        threads = [
            threading.Thread(
                target=lambda i=i: results.__setitem__(i, runners[i].run()), daemon=True
            )
            for i in range(2)
        ]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 30.0
        while 0 not in results and time.monotonic() < deadline:
            time.sleep(0.1)
        for r in runners:
            r.request_stop("test over")
        for t in threads:
            t.join(10.0)
    finally:
        for v in vehicles:
            v.stop()
    follower = results[1]
    assert follower.policy_errors == 0
    assert follower.ticks > 40
    from openconvoy.logs import read_log

    log = read_log(tmp_path / "deploy" / "vehicle_1.csv")
    coop = np.asarray(log["mode"]) == "coop"
    assert coop.sum() > 20
    # The follower moved under the learned policy's commands, behind the leader.
    assert np.nanmax(np.asarray(log["cmd_speed_mps"], dtype=float)[coop]) > 0.3
    assert np.nanmax(np.asarray(log["speed_mps"], dtype=float)) > 0.2
    gaps = np.asarray(log["gap_m"], dtype=float)
    assert np.nanmin(gaps) > 5.0


def test_train_config_rejects_unknown_keys(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text("total_steps = 10\n[randomization]\nper_rnage = [0, 0.5]\n")
    with pytest.raises(ValueError, match="unknown key.*per_rnage"):
        load_train_config(cfg)
    assert main(["train", "--config", str(cfg), "--out", str(tmp_path / "x")]) == 2


def test_default_config_is_residual_on_the_paper_controller() -> None:
    config = TrainConfig()
    assert config.env.base_policy == "paper"
    assert config.env.member_config == PRESETS["paper"].member
    assert config.randomization.per_range == (0.0, 0.6)


def test_base_none_trains_absolute_actions(tmp_path: Path) -> None:
    """``--base none``: no classical base; the network's action spans the recorded range."""
    cfg = tmp_path / "abs.toml"
    cfg.write_text(
        "validation_seeds = []\n[env]\naction_low = [0.0, -0.5]\naction_high = [5.0, 0.5]\n"
    )
    run = tmp_path / "abs"
    assert (
        main(
            [
                "train",
                "--config",
                str(cfg),
                "--base",
                "none",
                "--steps",
                "512",
                "--envs",
                "1",
                "--out",
                str(run),
                "--no-progress",
            ]
        )
        == 0
    )
    policy = load_learned(run / "policy.zip")
    assert policy.meta.base is None and policy.meta.residual_scale == (0.0, 0.0)
    assert policy.meta.action_low == (0.0, -0.5) and policy.meta.action_high == (5.0, 0.5)
    actions = np.array([policy.act(o) for o in sample_observations(policy, n=100)])
    assert np.all((actions[:, 0] >= 0.0) & (actions[:, 0] <= 5.0))
    assert np.all(np.abs(actions[:, 1]) <= 0.5 + 1e-6)


def test_per_sweep_compares_learned_and_classical(
    ppo_run: Path, ppo_npz: Path, tmp_path: Path
) -> None:
    """One sweep with the .zip, the .npz and the paper controller side by side."""
    out = tmp_path / "sweep"
    code = main(
        [
            "experiment",
            "per-sweep",
            "--policy",
            str(ppo_run / "policy.zip"),
            "--policy",
            str(ppo_npz),
            "--policy",
            "paper",
            "--pers",
            "0,0.3",
            "--seeds",
            "1",
            "--duration",
            "4",
            "--out",
            str(out),
            "--jobs",
            "1",
            "--quiet",
            "--no-plots",
        ]
    )
    assert code == 0
    rows = json.loads((out / "summary.json").read_text())["rows"]
    assert len(rows) == 6
    by = {(r["policy"], r["per"]): r for r in rows}
    for per in (0.0, 0.3):
        zip_row, npz_row = by[(str(ppo_run / "policy.zip"), per)], by[(str(ppo_npz), per)]
        # The same network, two artifacts: the same numbers, to the bit.
        assert {**zip_row, "policy": ""} == {**npz_row, "policy": ""}
        assert zip_row["collisions"]["max"] == 0
    lines = (out / "summary.csv").read_text().splitlines()
    zip_lines = [ln.partition(",")[2] for ln in lines if ln.startswith(str(ppo_run / "policy.zip"))]
    npz_lines = [ln.partition(",")[2] for ln in lines if ln.startswith(str(ppo_npz))]
    assert len(zip_lines) == 2 and zip_lines == npz_lines


def test_trained_zip_acts_batched_and_validates_as_run_by_run(ppo_run: Path) -> None:
    """One SB3 forward pass over a batch gives each row's ``act``; the batched validation
    of the trained file gives ``run_sim``'s numbers."""
    policy = load_learned(ppo_run / "policy.zip")
    obs = sample_observations(policy, n=64)
    rows = np.array([copy.deepcopy(policy).act(o) for o in obs])
    np.testing.assert_allclose(
        policy.act_batch(obs.reshape(16, 4, -1)).reshape(64, 2), rows, atol=1e-6
    )
    args = (ppo_run / "policy.zip", (0.0, 0.6), (1000,))
    batched, single = (
        validate(*args, duration_s=4.0),
        validate(*args, duration_s=4.0, batched=False),
    )
    for b, s in zip(batched.metrics, single.metrics):
        assert b["collisions"] == s["collisions"]
        for key in ("p95_platooning_error_m", "mean_speed_difference_mps", "min_gap_m"):
            assert b[key] == pytest.approx(s[key], abs=1e-6), key


def test_base_none_brings_the_from_scratch_defaults(tmp_path: Path) -> None:
    """``--base none`` switches to absolute actions with their own defaults (action range,
    no latched emergency stop while training); what a config chose stays."""
    from openconvoy.cli import build_parser
    from openconvoy.train.commands import train_config_from_args
    from openconvoy.train.randomization import (
        ABSOLUTE_ACTION_BOUNDS,
        SCRATCH_REWARD,
        TRAIN_REWARD,
        TRAIN_SHAPING,
    )

    parse = build_parser().parse_args
    scratch = train_config_from_args(parse(["train", "--base", "none"])).env
    assert scratch.base_policy == "" and scratch.bounds == ABSOLUTE_ACTION_BOUNDS
    assert scratch.emergency_stop is False and TrainConfig().env.emergency_stop is True
    assert scratch.reward == SCRATCH_REWARD and TrainConfig().env.reward == TRAIN_REWARD
    assert scratch.shaping == TRAIN_SHAPING == TrainConfig().env.shaping  # one bonus for both
    assert train_config_from_args(parse(["train", "--base", "none"])).ppo.use_sde is True
    assert TrainConfig().ppo.use_sde is False
    cfg = tmp_path / "chosen.toml"
    cfg.write_text("[env]\naction_low = [0.0, -0.5]\naction_high = [5.0, 0.5]\n")
    chosen = train_config_from_args(parse(["train", "--config", str(cfg), "--base", "none"])).env
    assert chosen.bounds == ((0.0, -0.5), (5.0, 0.5))
    # The run size and PPO settings of the kind come with it; flags given win.
    run = train_config_from_args(parse(["train", "--base", "none"]))
    assert (run.n_envs, run.budget_s, run.ppo.n_steps) == (64, None, 32)  # steps, not clock
    assert (
        train_config_from_args(parse(["train", "--base", "none", "--budget", "1m"])).budget_s == 60
    )
    assert TrainConfig().budget_s is None and TrainConfig().n_envs == 32
    # The README's from-scratch run: `--base none`, written out.
    example = Path(__file__).parents[2] / "openconvoy/train/examples/from-scratch.toml"
    assert load_train_config(example) == run
    assert run.env.reward == SCRATCH_REWARD and run.ppo.use_sde and not run.env.emergency_stop
    assert run.env.bounds == ABSOLUTE_ACTION_BOUNDS


def test_a_from_scratch_gsde_policy_exports_and_sweeps_as_its_zip(tmp_path: Path) -> None:
    """``--base none`` trains with gSDE; its deterministic action is the Gaussian mean, so
    the ``.npz`` acts as SB3's ``predict`` (within 1e-5) and its sweep's summary.csv is
    the ``.zip``'s byte for byte (both run one numpy forward)."""
    from stable_baselines3 import PPO

    run = tmp_path / "scratch"
    argv = ["train", "--base", "none", "--steps", "512", "--envs", "1", "--no-progress"]
    cfg = tmp_path / "c.toml"
    cfg.write_text("validation_seeds = []\n")
    assert main([*argv, "--config", str(cfg), "--out", str(run)]) == 0
    model = PPO.load(str(run / "policy.zip"), device="cpu")
    assert model.policy.use_sde  # what made export refuse it before
    npz_path = export_policy(run, tmp_path / "scratch.npz")
    npz = load_learned(npz_path)
    obs = sample_observations(npz, n=200)
    assert _worst_against_predict(npz, model, obs) <= 1e-5
    assert _worst_against_predict(load_learned(run / "policy.zip"), model, obs) <= 1e-5
    zipped = _sweep_csv(run / "policy.zip", tmp_path / "sweep-zip")
    assert zipped == _sweep_csv(npz_path, tmp_path / "sweep-npz")


def test_a_wall_clock_budget_too_small_to_learn_is_an_error(tmp_path: Path, capsys) -> None:
    """``--budget 1s`` stops before the first update: an error (exit 2), not a policy."""
    cfg = tmp_path / "c.toml"
    cfg.write_text("validation_seeds = []\n")
    argv = ["train", "--config", str(cfg), "--budget", "1s", "--envs", "32", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("training ppo for 600000 agent steps"), err
    assert len(err) == 2 and err[1].startswith(
        "openconvoy: error: the wall-clock budget of 1 s stopped learning after "
    ), err
    assert "before the network's first update (4096 steps): nothing was learned" in err[1]
    assert not (tmp_path / "r" / "policy.zip").exists()


def test_training_validates_its_base_beside_it_and_warns_when_worse(ppo_run: Path) -> None:
    """``validation.json`` holds the base's validation on the same grid; ``train`` prints
    the two side by side and a warning when the trained policy scores worse."""
    from openconvoy.train.validate import Validation, comparison_lines, validate

    report = json.loads((ppo_run / "validation.json").read_text())
    config = load_train_config(ppo_run / "config.toml")
    grid = (config.validation_pers, config.validation_seeds)
    base = validate("paper", *grid, duration_s=config.validation_duration_s)
    assert report["base"]["path"] == "paper"
    assert report["base"]["objective"] == pytest.approx(base.objective, rel=1e-12)
    chosen = next(v for v in report["validations"] if v["path"] == report["chosen"])
    trained = validate(ppo_run / "policy.zip", *grid, duration_s=config.validation_duration_s)
    assert trained.objective == pytest.approx(chosen["objective"], rel=1e-12)
    lines = comparison_lines(trained, base)
    assert lines[0].startswith("validation (1 run)") and "base paper" in lines[0]
    objective = lines[1].split()
    assert float(objective[-2]) == pytest.approx(trained.objective, rel=1e-3)
    assert float(objective[-1]) == pytest.approx(base.objective, rel=1e-3)
    warned = lines[-1].startswith("warning: the trained policy validates worse than paper")
    assert warned == (trained.objective > base.objective)
    # Swapped, exactly one of the two orders warns (unless they tie).
    better, worse = sorted((trained, base), key=lambda v: v.objective)
    assert not comparison_lines(better, worse)[-1].startswith("warning")
    if better.objective < worse.objective:
        assert comparison_lines(worse, better)[-1].startswith("warning")
    assert isinstance(trained, Validation)
