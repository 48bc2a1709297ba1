"""The plug-in API (issue 23): whole policies and components from Python, their load-time
checks, the spec grammar, entry points, the batched path and ``tune``."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import MemberConfig
from openconvoy.experiments.runs import RunConfig, run_sim
from openconvoy.policies import ClassicalPolicy, load_policy
from openconvoy.policies.plugin import BatchPluginPolicy, PluginPolicy
from openconvoy.policies.spec import classical_config, with_policy_args

ROOT = Path(__file__).resolve().parents[2]
PLUGINS = "tests/data/plugins"


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    """Plug-in paths in specs and policy files are relative to the current directory."""
    monkeypatch.chdir(ROOT)


def _files(run_dir: Path) -> dict[str, bytes]:
    return {n: (run_dir / n).read_bytes() for n in ("log.csv", "metrics.json")}


def test_plugin_components_equal_to_ours_reproduce_the_paper_to_the_byte(tmp_path):
    """ρ, τ, σ, χ_v and χ_θ all plug-ins that compute what ours do: the same log and
    metrics, byte for byte, at 30 % loss (the stale-target caps run too)."""
    config = load_policy(f"{PLUGINS}/equal.toml")
    assert isinstance(config, ClassicalPolicy)
    assert len(config.plugins) == 5, config.plugins
    for spec, out in (("paper", "a"), (f"{PLUGINS}/equal.toml", "b")):
        run_sim(RunConfig(policy=spec, per=0.3, seed=4, duration_s=25.0), tmp_path / out)
    assert _files(tmp_path / "a") == _files(tmp_path / "b")


def test_plugin_spacing_equal_to_cth_reproduces_the_presets_summary_csv(tmp_path):
    """A 2-PER × 2-seed sweep of ``cacc-allpred`` (batched) and of the same policy with
    examples/my_spacing.py (q = 0, run per run): the same summary.csv, byte for byte."""
    head = '[experiment]\npolicies = ["cth"]\npers = [0.0, 0.3]\nseeds = 2\nduration_s = 15.0\n'
    head += '[policy.cth]\nbase = "cacc-allpred"\n'
    plugin = (
        '[policy.cth.member.spacing]\nkind = "examples/my_spacing.py:Quadratic"\n'
        "params = { standstill_m = 2.0, headway_s = 0.6 }\n"
    )
    for name, text in (("builtin", head), ("plugin", head + plugin)):
        (tmp_path / f"{name}.toml").write_text(text)
        argv = ["experiment", "per-sweep", "--config", str(tmp_path / f"{name}.toml")]
        assert main([*argv, "--out", str(tmp_path / name), "--jobs", "1"]) == 0
    builtin = (tmp_path / "builtin" / "summary.csv").read_bytes()
    assert builtin == (tmp_path / "plugin" / "summary.csv").read_bytes()
    assert builtin.count(b"\ncth,") == 2


def test_a_whole_policy_from_a_file_or_a_module_with_arguments(tmp_path, monkeypatch):
    p = load_policy("examples/my_policy.py:GapKeeper?kp=0.7")
    assert isinstance(p, PluginPolicy) and not isinstance(p, BatchPluginPolicy)
    assert (p.inner.kp, p.control_rate_hz, p.member_config, p.name) == (
        0.7,
        20.0,
        None,
        "examples/my_policy.py:GapKeeper",
    )
    # The same class by module path (the current directory is on the import path).
    for name in ("mylab", "mylab.ctl"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    (tmp_path / "mylab").mkdir()
    (tmp_path / "mylab" / "ctl.py").write_text((ROOT / "examples/my_policy.py").read_text())
    monkeypatch.chdir(tmp_path)
    q = load_policy("mylab.ctl:GapKeeper?kp=0.7")
    from openconvoy.envs import ConvoyEnv

    env = ConvoyEnv()
    obs, _ = env.reset(seed=0)
    for _ in range(40):
        obs, *_ = env.step({a: p.act(o) for a, o in obs.items()})
    action = p.act(obs["follower_2"])
    assert action[0] > 0.1  # a real observation: the predecessor heard, moving
    np.testing.assert_array_equal(action, q.act(obs["follower_2"]))
    # A policy TOML naming the plug-in, with its keyword arguments.
    toml = tmp_path / "mine.toml"
    toml.write_text(
        f'[policy]\nplugin = "{ROOT}/examples/my_policy.py:GapKeeper"\n[policy.args]\nkp = 0.9\n'
    )
    r = load_policy(str(toml))
    assert isinstance(r, PluginPolicy) and r.inner.kp == 0.9 and r.name == "mine"
    assert load_policy(f"{toml}?kp=0.2").inner.kp == 0.2  # --policy-arg wins over the file


def test_policy_args_fold_into_the_spec_and_reach_the_run(tmp_path, capsys):
    spec = with_policy_args("examples/my_policy.py:GapKeeper", ["kp=0.5", "max_speed_mps=3"])
    assert spec == "examples/my_policy.py:GapKeeper?kp=0.5&max_speed_mps=3"
    with pytest.raises(ConfigError, match="not a Python plug-in policy"):
        with_policy_args("paper", ["kp=1"])
    argv = ["sim", "--policy", "examples/my_policy.py:GapKeeper", "--policy-arg", "kp=0.5"]
    assert main([*argv, "--duration", "3", "--out", str(tmp_path), "--no-plots"]) == 0
    assert (
        'policy = "examples/my_policy.py:GapKeeper?kp=0.5"' in (tmp_path / "run.toml").read_text()
    )


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        (f"{PLUGINS}/faulty.py:NoAct", ["NoAct has no method act()"]),
        (f"{PLUGINS}/faulty.py:WrongSignature", ["WrongSignature.act()", "1 argument"]),
        (f"{PLUGINS}/faulty.py:BadMemberConfig", ["member_config is a str", "MemberConfig"]),
        (f"{PLUGINS}/faulty.py:Slow?speed=1", ["Slow(delay_s: float = 0.2)", "speed"]),
        (f"{PLUGINS}/faulty.py:Missing", ["has no 'Missing'"]),
        (f"{PLUGINS}/nofile.py:X", ["no such file", "nofile.py"]),
        ("nosuchlab.ctl:X", ["no module named 'nosuchlab'"]),
        ("gap-keeper-not-installed", ["unknown policy", "installed plug-in"]),
        (f"{PLUGINS}/faulty.py:Raises+ladder", ["+ladder is for classical policies"]),
    ],
)
def test_a_bad_plugin_is_one_line_at_load_time_exit_2(spec, words, tmp_path, capsys):
    assert main(["sim", "--policy", spec, "--out", str(tmp_path), "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("openconvoy: error: "), err
    for w in words:
        assert w in err[0], err[0]


@pytest.mark.parametrize(
    ("table", "words"),
    [
        ('spacing = "examples/my_spacing.py:Nope"', ["spacing", "has no 'Nope'"]),
        (
            'spacing = { kind = "examples/my_spacing.py:Quadratic", params = { gap = 1 } }',
            ["Quadratic", "gap"],
        ),
        ('trigger = "tests/data/plugins/equal.py:PD"', ["PD has no method should_send()"]),
        ('topology = "ring"', ["topology 'ring'", "installed topology plug-in"]),
        (
            'topology = "tests/data/plugins/faulty.py:RaisingTopology"',
            ["keeps(1, j, 2) raised KeyError: 0"],
        ),
        (
            'spacing = "tests/data/plugins/faulty.py:NanSpacing"',
            ["pair_gap(0, 4, 4) = nan; expected a finite gap >= 0 m"],
        ),
    ],
)
def test_a_bad_component_is_one_line_naming_it(table, words, tmp_path, capsys):
    toml = tmp_path / "p.toml"
    toml.write_text(f'[policy]\nbase = "paper"\n[policy.member]\n{table}\n')
    assert main(["sim", "--policy", str(toml), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for w in words:
        assert w in err[0], err[0]


def test_entry_points_list_in_presets_and_load_by_name(tmp_path, monkeypatch, capsys):
    """An installed package (its dist-info's entry_points.txt, as pip writes it) adds a
    policy and a spacing policy by name."""
    pkg, info = tmp_path / "eplab", tmp_path / "eplab-0.1.dist-info"
    pkg.mkdir()
    info.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "ctl.py").write_text((ROOT / "examples/my_policy.py").read_text())
    (pkg / "spacing.py").write_text((ROOT / "examples/my_spacing.py").read_text())
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: eplab\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[openconvoy.policies]\ngap-keeper = eplab.ctl:GapKeeper\n\n"
        "[openconvoy.spacing]\nmy-quadratic = eplab.spacing:Quadratic\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["presets"]) == 0
    out = capsys.readouterr().out
    assert "gap-keeper" in out and "eplab.ctl:GapKeeper" in out
    assert "my-quadratic" in out and "eplab.spacing:Quadratic" in out
    p = load_policy("gap-keeper?kp=0.6")
    assert isinstance(p, PluginPolicy) and p.inner.kp == 0.6
    cacc = classical_config("cacc-allpred")
    spacing = dataclasses.replace(cacc.member.spacing, kind="my-quadratic", params={})
    member = dataclasses.replace(cacc.member, spacing=spacing)
    assert MemberConfig(spacing=spacing).spacing.is_plugin and member.plugins == [
        "spacing my-quadratic"
    ]


def test_act_batch_runs_batched_only_when_bit_equal_to_act(tmp_path):
    from openconvoy.experiments.batched.run import refusal, run_batch

    good = RunConfig(policy=f"{PLUGINS}/batchable.py:Batchable", duration_s=8.0)
    bad = dataclasses.replace(good, policy=f"{PLUGINS}/batchable.py:Inexact")
    assert refusal(good) is None
    why = refusal(bad)
    assert why is not None and "act_batch differs from its act at tick" in why
    assert "has no act_batch" in (
        refusal(dataclasses.replace(good, policy="examples/my_policy.py:GapKeeper")) or ""
    )
    spacing = refusal(dataclasses.replace(good, policy="examples/my_spacing.toml"))
    assert spacing is not None and "plug-in spacing examples/my_spacing.py:Quadratic" in spacing
    # Batched, the bit-equal plug-in gives the per-run files to the byte.
    configs = [dataclasses.replace(good, per=p, seed=1) for p in (0.0, 0.4)]
    batched = run_batch(configs)
    for rc, res in zip(configs, batched):
        run_sim(rc, tmp_path / f"per{rc.per}")
        assert res["files"]["log.csv"] == (tmp_path / f"per{rc.per}" / "log.csv").read_bytes()


def test_tune_searches_a_plugins_declared_parameters(tmp_path):
    from openconvoy.train.tune import TuneConfig, applicable, base_candidate, tune

    whole = base_candidate("examples/my_policy.py:GapKeeper")
    assert applicable(whole) == ["args.kp"]
    spacing = base_candidate("examples/my_spacing.toml")
    assert "member.spacing.params.headway_s" in applicable(spacing)
    assert "member.spacing.headway_s" not in applicable(spacing)  # the built-in's, not used
    seen = []

    def evaluate(candidate):
        seen.append(candidate.args["kp"] if "kp" in candidate.args else None)
        return abs(candidate.args.get("kp", 0.4) - 1.0)

    config = TuneConfig(base="examples/my_policy.py:GapKeeper", trials=3, pers=(0.0,), seeds=(0,))
    result = tune(config, evaluate=evaluate)
    assert len(seen) == 4 and all(0.05 <= k <= 2.0 for k in seen[1:])  # the base, then 3 trials
    assert result.best.plugin == "examples/my_policy.py:GapKeeper"
    assert result.best_value == min(abs(k - 1.0) for k in seen[1:])
