"""Training plug-ins (issue 23, item 5): a reward function of one's own in ``train``, and
a plug-in policy as the residual base (``train --base file.py:Name``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.train.randomization import EnvSpec, Randomization, RandomizedConvoyEnv

ROOT = Path(__file__).resolve().parents[2]
SMOOTH = "examples/my_reward.py:Smooth?weight=0.2"


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    monkeypatch.chdir(ROOT)


def test_the_reward_plugin_gets_the_envs_reward_and_the_agents_info():
    """Same seed, same actions: the plug-in's reward is the env's minus 0.2 × |accel|."""
    r = Randomization(per_range=(0.2, 0.2))
    plain = RandomizedConvoyEnv(EnvSpec(max_time_s=3.0), r)
    smooth = RandomizedConvoyEnv(EnvSpec(max_time_s=3.0, reward_fn=SMOOTH), r)
    plain.reset(seed=5)
    smooth.reset(seed=5)
    rng = np.random.default_rng(0)
    checked = 0
    while plain.agents:
        actions = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in plain.agents}
        _, want, _, _, infos = plain.step(actions)
        _, got, _, _, _ = smooth.step(actions)
        for a in want:
            assert got[a] == want[a] - 0.2 * abs(infos[a]["accel_mps2"])
            checked += abs(infos[a]["accel_mps2"]) > 0.01
    assert checked > 50


def test_a_short_ppo_run_trains_on_a_custom_reward(tmp_path, capsys):
    cfg = tmp_path / "train.toml"
    cfg.write_text(f'validation_seeds = []\ncheckpoint_every = 0\n[env]\nreward_fn = "{SMOOTH}"\n')
    argv = ["train", "--config", str(cfg), "--steps", "512", "--envs", "1"]
    assert main([*argv, "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert f"the reward plug-in {SMOOTH} runs in Python" in err
    assert (tmp_path / "run" / "policy.zip").is_file()
    assert f'reward_fn = "{SMOOTH}"' in (tmp_path / "run" / "config.toml").read_text()


def test_a_bad_reward_plugin_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "train.toml"
    cfg.write_text('[env]\nreward_fn = "examples/my_reward.py:Smooth?wieght=1"\n')
    assert main(["train", "--config", str(cfg), "--out", str(tmp_path / "run")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "Smooth(weight: float = 0.1) cannot take {'wieght': 1}" in line


def test_a_plugin_policy_is_a_residual_base(tmp_path, capsys):
    """``train --base examples/my_policy.py:GapKeeper --policy-arg kp=0.5``: the run
    records the plug-in by reference; the trained policy adds its network to the
    plug-in's action, per vehicle and batched alike."""
    from openconvoy.envs import ConvoyEnv
    from openconvoy.policies.learned import load_learned
    from openconvoy.policies.plugin import load_plugin_policy

    argv = ["train", "--base", "examples/my_policy.py:GapKeeper", "--policy-arg", "kp=0.5"]
    argv += ["--steps", "512", "--envs", "1", "--out", str(tmp_path / "run"), "--no-progress"]
    assert main(argv) == 0
    assert "plug-in residual base examples/my_policy.py:GapKeeper?kp=0.5" in capsys.readouterr().err
    policy = load_learned(tmp_path / "run" / "policy.zip")
    assert policy.meta.base is None
    assert policy.meta.base_plugin == "examples/my_policy.py:GapKeeper?kp=0.5"
    base = load_plugin_policy(policy.meta.base_plugin)
    env = ConvoyEnv(member_config=policy.member_config)
    obs, _ = env.reset(seed=0)
    for _ in range(30):
        obs, *_ = env.step({a: policy.act(o) for a, o in obs.items()})
    o = obs["follower_2"]
    want = policy.meta.to_si(policy.normalized_action(o), base.act(o))
    np.testing.assert_array_equal(policy.act(o), want)
    batch = np.stack([obs["follower_1"], o])
    policy.reset()
    np.testing.assert_allclose(policy.act_batch(batch)[1], want, atol=1e-5)


def test_observation_features_reach_the_network_wherever_the_policy_runs(tmp_path, capsys):
    """``[env] obs_features``: the network sees the layout's numbers and the plug-in's;
    the trained .zip and its .npz export record the plug-in and compute it from the
    observation at act time; a plug-in that now gives another count is refused."""
    import dataclasses

    from openconvoy.core.errors import InputFileError
    from openconvoy.policies.learned import load_learned

    cfg = tmp_path / "train.toml"
    cfg.write_text(
        "validation_seeds = []\ncheckpoint_every = 0\n"
        '[env]\nobs_features = "examples/my_features.py:GapRatio"\n'
    )
    run = tmp_path / "run"
    argv = ["train", "--config", str(cfg), "--steps", "512", "--envs", "1"]
    assert main([*argv, "--out", str(run), "--no-progress"]) == 0
    assert (
        "observation-features plug-in examples/my_features.py:GapRatio" in capsys.readouterr().err
    )
    assert main(["export", str(run), "--out", str(run / "p.npz")]) == 0
    zipped, exported = load_learned(run / "policy.zip"), load_learned(run / "p.npz")
    size = zipped.layout.size
    for policy in (zipped, exported):
        assert (policy.meta.obs_features, policy.meta.feature_size) == (
            "examples/my_features.py:GapRatio",
            2,
        )
        assert policy.meta.obs_mean is not None and policy.meta.obs_mean.shape == (size + 2,)
    from openconvoy.envs import ConvoyEnv

    env = ConvoyEnv(member_config=zipped.member_config)
    obs, _ = env.reset(seed=1)
    for _ in range(40):
        obs, *_ = env.step({a: zipped.act(o) for a, o in obs.items()})
    o = obs["follower_2"]
    extended = zipped._extend(o)
    assert extended.shape == (size + 2,) and extended[size] == pytest.approx(1.0, abs=0.2)
    np.testing.assert_allclose(zipped.act(o), exported.act(o), atol=1e-5)
    with pytest.raises(InputFileError, match="gives 2 features; the policy was trained with 3"):
        dataclasses.replace(
            zipped.meta, feature_size=3, obs_mean=None, obs_var=None
        ).make_features()
