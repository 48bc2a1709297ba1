"""examples/ (your own controller): a custom policy, spacing policy and trigger, each through
``sim``, a 2-PER ``experiment per-sweep``, ``tune`` (3 trials) and the netns ``demo``,
writing the same log and metrics files as a built-in preset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.comms.netns import netns_unavailable_reason
from openconvoy.logs import COLUMNS, read_log
from openconvoy.policies import load_policy

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = {
    "policy": "examples/my_policy.py:GapKeeper",
    "spacing": "examples/my_spacing.toml",
    "trigger": "examples/my_trigger.toml",
}
SIM = ["--duration", "8", "--no-plots"]


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    """The examples name their plug-in files relative to the repository root."""
    monkeypatch.chdir(ROOT)


def _listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def preset(tmp_path_factory) -> dict[str, Path]:
    """``paper`` through ``sim`` and a 2-PER sweep: the files every example must match."""
    d = tmp_path_factory.mktemp("preset")
    assert main(["sim", "--policy", "paper", *SIM, "--out", str(d / "sim")]) == 0
    argv = ["experiment", "per-sweep", "--policy", "paper", "--pers", "0,0.2", "--seeds", "1"]
    argv += ["--duration", "8", "--jobs", "1", "--quiet", "--no-batched"]
    assert main([*argv, "--out", str(d / "sweep")]) == 0
    return {"sim": d / "sim", "sweep": d / "sweep"}


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_example_through_sim(example, preset, tmp_path):
    out = tmp_path / "sim"
    assert main(["sim", "--policy", EXAMPLES[example], *SIM, "--out", str(out)]) == 0
    assert _listing(out) == _listing(preset["sim"])
    ours, theirs = read_log(out / "log.csv"), read_log(preset["sim"] / "log.csv")
    assert list(ours) == list(theirs) and set(COLUMNS) <= set(ours)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics.keys() == json.loads((preset["sim"] / "metrics.json").read_text()).keys()
    assert metrics["collisions"] == 0 and metrics["p95_platooning_error_m"] < 1.0
    follower = ours["vehicle_id"] == 2
    if example == "trigger":  # broadcasts on change or after 0.3 s, not every 0.1 s
        paper_sent = theirs["msgs_sent"][theirs["vehicle_id"] == 2].max()
        assert ours["msgs_sent"][follower].max() < 0.5 * paper_sent
    if example == "spacing":  # 2 m + 0.6 s·v + 0.01 s²/m·v² between bumpers
        speed, desired = ours["speed_mps"][follower], ours["desired_gap_m"][follower]
        lengths = ours["length_m"][ours["vehicle_id"] == 1][0] + ours["length_m"][follower][0]
        v = np.maximum(speed, 0.0)
        np.testing.assert_allclose(desired, 2.0 + 0.6 * v + 0.01 * v * v + 0.5 * lengths, rtol=1e-6)


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_example_through_a_two_per_sweep(example, preset, tmp_path, capsys):
    argv = ["experiment", "per-sweep", "--policy", EXAMPLES[example], "--pers", "0,0.2"]
    argv += ["--seeds", "1", "--duration", "8", "--jobs", "1"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    assert "one ConvoyEnv per run" in capsys.readouterr().err  # said once, why
    rows = json.loads((tmp_path / "summary.json").read_text())["rows"]
    assert [r["per"] for r in rows] == [0.0, 0.2] and all(r["runs"] == 1 for r in rows)

    def shape(d: Path) -> list[str]:  # the files, with the policy's directory name generic
        return sorted(
            "/".join(["P" if i == 1 and parts[0] == "runs" else p for i, p in enumerate(parts)])
            for parts in (Path(f).parts for f in _listing(d))
            if parts[0] != "policies"  # inline policy files: a preset has none
        )

    assert shape(tmp_path) == shape(preset["sweep"])


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_example_through_tune(example, tmp_path):
    out = tmp_path / "tuned.toml"
    argv = ["tune", "--policy", EXAMPLES[example], "--trials", "3", "--per", "0", "0.2"]
    assert main([*argv, "--seeds", "0", "--duration", "8", "--out", str(out)]) == 0
    study = json.loads(out.with_suffix(".json").read_text())
    assert len(study["trials"]) == 3 and study["best_value"] <= study["base_value"] + 1e-12
    tuned = load_policy(str(out))  # the written policy loads and names the same plug-in
    assert EXAMPLES[example].split(":")[0].split(".")[0].split("/")[-1] in out.read_text()
    assert tuned.control_rate_hz == 20.0


@pytest.mark.e2e
@pytest.mark.netns
@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_example_through_the_netns_demo(example, tmp_path):
    """Three deploy processes over MAVLink and IPv6 multicast in a private namespace,
    driven by the example (8 s), then the pure simulation of the same scenario."""
    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    r = subprocess.run(
        [sys.executable, "-m", "openconvoy.cli", "demo", "--policy", EXAMPLES[example]]
        + ["--duration", "8", "--json", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    report = json.loads(r.stdout.strip().splitlines()[-1])
    assert report["deploy"]["collisions"] == 0 and report["sim"]["collisions"] == 0
    assert _listing(tmp_path / "sim") == ["log.csv", "metrics.json"]
    for vid in range(3):
        log = read_log(tmp_path / "deploy" / f"vehicle_{vid}.csv")
        assert set(COLUMNS) <= set(log)
        meta = json.loads((tmp_path / "deploy" / f"vehicle_{vid}.json").read_text())
        assert meta["policy_errors"] == 0
        if vid:  # followers time their policy's act
            assert meta["policy_act_s"]["p99"] < 0.05
    lines = (tmp_path / "deploy_1.txt").read_text()
    assert "policy act: median" in lines
