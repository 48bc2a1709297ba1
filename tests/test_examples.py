"""Every example in examples/ runs as a user would run it (issue 26 item 3), with numbers
checked: the custom scenario drives without a collision, the SB3 example trains, saves a
loadable model and scores the paper's controller as ``sim`` would, the RLlib example trains
a shared policy on the plug-ins and restores it, and the field convoy file loads,
simulates, and takes keys as its comments say."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from openconvoy.cli import main
from openconvoy.convoy import load_convoy

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
RLLIB_PYTHON = ROOT / ".venv-rllib" / "bin" / "python"
"""RLlib's own venv (``make test`` builds it: ray[rllib] pins gymnasium 1.2.2)."""


def _run(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *argv], capture_output=True, text=True, timeout=600, cwd=cwd
    )


def _printed(stdout: str) -> dict[str, float]:
    """The ``name value`` lines an example prints."""
    out = {}
    for line in stdout.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0] != "wrote":
            out[parts[0]] = float(parts[1])
    return out


def test_custom_scenario_runs_the_paper_controller_on_an_s_bend(tmp_path: Path) -> None:
    r = _run(str(EXAMPLES / "custom_scenario.py"), "--seconds", "40", "--per", "0.2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    got = _printed(r.stdout)
    assert got["collided"] == 0.0
    assert 12.0 < got["min_gap_m"] < 15.5  # the 15 m gap, kept through bends and a stop
    assert 0.0 < got["p95_platooning_error_m"] < 3.0


def test_custom_scenario_is_a_scenario_convoyenv_accepts() -> None:
    sys.path.insert(0, str(EXAMPLES))
    try:
        import custom_scenario
    finally:
        sys.path.remove(str(EXAMPLES))
    from openconvoy.envs import ConvoyEnv
    from openconvoy.envs.scenarios import Scenario

    scenario = custom_scenario.make_scenario(30.0)
    assert isinstance(scenario, Scenario) and scenario.n_vehicles == 4
    env = ConvoyEnv(scenario)
    assert env.possible_agents == ["follower_1", "follower_2", "follower_3"]
    assert env.max_time_s == 30.0
    assert custom_scenario.stop_and_go(27.0, 0.0) == 0.0


@pytest.mark.e2e
def test_train_sb3_example_trains_saves_and_evaluates(tmp_path: Path) -> None:
    out = tmp_path / "sb3"
    r = _run(str(EXAMPLES / "train_sb3.py"), "--steps", "512", "--out", str(out), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    got = _printed(r.stdout)
    assert (out / "ppo_follower.zip").is_file()
    from stable_baselines3 import PPO

    model = PPO.load(out / "ppo_follower.zip")
    assert model.observation_space.shape == (111,) and model.action_space.shape == (2,)
    # The paper's controller at PER 0.2 (seed 100), as `openconvoy sim` measures follower 1.
    assert 0.1 < got["paper_p95_m"] < 0.4
    assert got["trained_p95_m"] > 0.0


def _processes_naming(text: str) -> list[str]:
    """Command lines of this machine's processes that contain ``text``."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # gone meanwhile, or not a process
            continue
        if text in cmd:
            found.append(cmd)
    return found


def _run_rllib(*argv: str, cwd: Path, tmp: str) -> subprocess.CompletedProcess:
    """examples/train_rllib.py in .venv-rllib's python, Ray's folders under ``tmp``."""
    assert RLLIB_PYTHON.is_file(), f"{RLLIB_PYTHON} is missing: `make test` builds it"
    env = {**os.environ, "TMPDIR": tmp}
    return subprocess.run(
        [str(RLLIB_PYTHON), str(EXAMPLES / "train_rllib.py"), *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
        env=env,
    )


ITERATION = re.compile(r"^iteration (\d+) env_steps (\d+) return (\S+)$", re.M)
GREEDY = re.compile(r"^(saved|restored) greedy (\S+) (\S+)$", re.M)


@pytest.mark.e2e
def test_train_rllib_example_trains_a_shared_policy_and_restores_it(tmp_path: Path) -> None:
    """Two PPO iterations of 200 env steps on the two-follower env (reward and features
    plug-ins), a checkpoint, then a second process restores it: the same greedy action to
    the last bit, and training goes on from iteration 3 and 600 env steps. No Ray process
    is left behind."""
    # Ray's socket paths must stay under 108 bytes: a short folder, not tmp_path.
    ray_tmp = tempfile.mkdtemp(prefix="rl", dir="/tmp")
    try:
        common = ("--batch", "200", "--seconds", "5")
        out = tmp_path / "rllib"
        r = _run_rllib("--iterations", "2", *common, "--out", str(out), cwd=tmp_path, tmp=ray_tmp)
        assert r.returncode == 0, r.stderr[-3000:]
        # 111 layout numbers + GapRatio's 2: the features plug-in reached the policy.
        # 111 layout numbers + GapRatio's 2: the features plug-in reached the policy.
        assert "policy shared obs 113 critic own reward my_reward.py:Smooth?weight=0.2" in r.stdout
        rows = [(int(i), int(n), float(ret)) for i, n, ret in ITERATION.findall(r.stdout)]
        assert [(i, n) for i, n, _ in rows] == [(1, 200), (2, 400)]
        # 100-step episodes, 2 followers: each iteration ends two episodes.
        assert all(math.isfinite(ret) and ret != 0.0 for _, _, ret in rows)
        assert (out / "checkpoint" / "rllib_checkpoint.json").is_file()

        again = _run_rllib(
            "--restore",
            str(out / "checkpoint"),
            "--iterations",
            "1",
            *common,
            cwd=tmp_path,
            tmp=ray_tmp,
        )
        assert again.returncode == 0, again.stderr[-3000:]
        saved = dict((w, (a, b)) for w, a, b in GREEDY.findall(r.stdout))["saved"]
        restored = dict((w, (a, b)) for w, a, b in GREEDY.findall(again.stdout))["restored"]
        assert restored == saved  # printed as repr: bit for bit
        assert all(abs(float(v)) <= 10.0 for v in saved)  # a normalized residual, not junk
        [(i, n, ret)] = [(int(i), int(n), float(x)) for i, n, x in ITERATION.findall(again.stdout)]
        assert (i, n) == (3, 600) and math.isfinite(ret)  # counters came back with it

        assert _processes_naming(ray_tmp) == []  # raylet, GCS, workers: all stopped
        assert not [p for p in os.listdir(ray_tmp) if p.startswith("ray")]  # folder removed
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)


@pytest.mark.e2e
def test_train_rllib_example_trains_mappo_style_with_a_central_critic(tmp_path: Path) -> None:
    """``--critic central``: each follower observes itself then the other (2 × 113), the
    critic reads all of it and the trained actor only its own part; two iterations run."""
    ray_tmp = tempfile.mkdtemp(prefix="rl", dir="/tmp")
    try:
        argv = ("--critic", "central", "--iterations", "2", "--batch", "200", "--seconds", "5")
        r = _run_rllib(*argv, "--out", str(tmp_path / "c"), cwd=tmp_path, tmp=ray_tmp)
        assert r.returncode == 0, r.stderr[-3000:]
        assert "policy shared obs 226 critic central" in r.stdout
        rows = [(int(i), int(n), float(ret)) for i, n, ret in ITERATION.findall(r.stdout)]
        assert [(i, n) for i, n, _ in rows] == [(1, 200), (2, 400)]
        assert all(math.isfinite(ret) and ret != 0.0 for _, _, ret in rows)
        # The greedy action with the other follower's 113 numbers replaced by noise.
        assert "actor reads own 113 of 226: yes" in r.stdout
        assert (tmp_path / "c" / "checkpoint" / "rllib_checkpoint.json").is_file()
        assert _processes_naming(ray_tmp) == []
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)


def test_render_cut_in_writes_an_animated_gif(tmp_path: Path) -> None:
    out = tmp_path / "cut-in.gif"
    r = _run(str(EXAMPLES / "render_cut_in.py"), "--seconds", "2", "--out", str(out), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"wrote {out} (10 frames)"  # 40 ticks, one frame every 4
    from PIL import Image

    with Image.open(out) as gif:
        assert gif.format == "GIF" and gif.n_frames == 10 and gif.size == (900, 100)
        assert gif.info["duration"] == 200  # 4 ticks at 20 Hz: real time


def test_field_convoy_file_loads_and_simulates(tmp_path: Path) -> None:
    convoy = load_convoy(EXAMPLES / "field" / "convoy.toml")
    assert convoy.vehicles == ("1/10", "1/6", "1/10")
    assert convoy.safety.speed_cap_mps == 3.0 and convoy.v2v.keys.endswith("convoy.keys")
    out = tmp_path / "sim"
    args = ["sim", "--convoy", str(EXAMPLES / "field" / "convoy.toml"), "--policy"]
    assert (
        main(
            [*args, "paper+ladder", "--duration", "10", "--quiet", "--no-plots", "--out", str(out)]
        )
        == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["collisions"] == 0 and metrics["min_gap_m"] > 14.0


def test_field_steps_make_the_keys_a_deploy_needs(tmp_path: Path) -> None:
    from openconvoy.bridge.deploy import vehicle_authenticator
    from openconvoy.comms.security.keystore import KeyFileError

    field = tmp_path / "field"
    shutil.copytree(EXAMPLES / "field", field)
    convoy = field / "convoy.toml"
    assert load_convoy(convoy).v2v.auth_required  # signed unless auth = "off" is written
    with pytest.raises(KeyFileError, match="holds no convoy keys"):  # V2V fails closed
        vehicle_authenticator(load_convoy(convoy), 1, str(convoy))
    assert main(["keys", "init", "--convoy", str(convoy)]) == 0
    for vid in (0, 1, 2):
        assert main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", str(vid)]) == 0
    keys = field / "convoy.keys"
    assert {p.name for p in keys.iterdir()} >= {
        "authority.key",
        "authority.cert",
        *(f"vehicle-{i}.{ext}" for i in (0, 1, 2) for ext in ("key", "cert")),
    }
    assert vehicle_authenticator(load_convoy(convoy), 1, str(convoy)) is not None
