"""Safety stays ours (issue 23, item 4): whatever a plug-in policy does, the one tick
decides. Each broken policy gives its documented outcome (docs/your-controller.md,
"What the platform enforces"): at load, one line and exit 2; while running, a policy
error — counted, an event naming it, the follower stopped for the rest of the run — the
same in ``sim`` and in ``deploy``'s runner."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.core.policy import ActGuard, PolicyFailure, make_action
from openconvoy.experiments.runs import RunConfig, run_sim
from openconvoy.policies import load_policy
from tests.bridge.test_runner import follower_setup  # the runner tests' fake vehicle and clock

ROOT = Path(__file__).resolve().parents[2]
FAULTY = "tests/data/plugins/faulty.py"


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    monkeypatch.chdir(ROOT)


def test_a_missing_method_is_one_line_at_load_time(tmp_path, capsys):
    assert main(["sim", "--policy", f"{FAULTY}:NoAct", "--out", str(tmp_path)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == (
        f"openconvoy: error: policy {FAULTY}:NoAct: NoAct has no method act() (the protocol needs it)"
    )
    assert not (tmp_path / "log.csv").exists()


def _run(name: str, tmp_path: Path) -> tuple[list[dict], dict, dict]:
    """Run the paper scenario 2 s with ``faulty.py:name`` (sim): events, log, metrics."""
    from openconvoy.logs import read_log

    result = run_sim(RunConfig(policy=f"{FAULTY}:{name}", duration_s=2.0), tmp_path)
    return result.events, read_log(tmp_path / "log.csv"), result.metrics


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        (
            "WrongShape",
            "policy error: action has shape (3,), not (2,): [speed_mps, heading_change_rad]",
        ),
        ("NotANumber", "policy error: non-finite action nan, 0.0"),
        ("Raises", "policy error: RuntimeError: boom"),
    ],
)
def test_a_bad_action_or_an_exception_stops_the_follower_at_once(name, reason, tmp_path):
    events, log, metrics = _run(name, tmp_path)
    assert [(e["t_s"], e["vehicle_id"], e["reason"]) for e in events] == [
        (0.0, 1, reason),
        (0.0, 2, reason),
    ]
    for vid in (1, 2):
        rows = log["vehicle_id"] == vid
        commanded = log["cmd_speed_mps"][rows][:-1]  # the last row has no command
        assert np.all(commanded == 0.0) and set(log["mode"][rows][:-1]) == {"failsafe"}
        assert np.all(log["speed_mps"][rows] == 0.0)  # never moved
    assert metrics["collisions"] == 0


def test_a_200_ms_act_is_a_policy_error_after_three_late_calls(tmp_path):
    """Four control periods per call: the third late call in a row (tick 2, t = 0.1 s)
    stops the follower; ``act`` is not called again (the run costs 6 calls, not 80)."""
    events, log, _ = _run("Slow", tmp_path)
    assert [(e["t_s"], e["vehicle_id"]) for e in events] == [(0.1, 1), (0.1, 2)]
    for e in events:
        assert e["reason"].startswith("policy error: act took 2")
        assert e["reason"].endswith("ms, over the 50 ms control period 3 times in a row")
    rows = log["vehicle_id"] == 1
    assert list(log["cmd_speed_mps"][rows][:3]) == [0.5, 0.5, 0.0]  # two ticks drove
    assert set(log["mode"][rows][2:-1]) == {"failsafe"}


def test_act_guard_counts_with_an_injected_clock():
    t = [0.0]

    class Policy:
        def act(self, obs):
            t[0] += 0.06 if obs[0] > 0 else 0.01
            return make_action(1.0, 0.0)

    guard = ActGuard(Policy(), 0.05, clock=lambda: t[0])  # type: ignore[arg-type]
    slow, fast = np.ones(1), np.zeros(1)
    # Late, late, on time: the count starts again; then three late in a row fail.
    for obs in (slow, slow, fast, slow, slow):
        assert not isinstance(guard(obs), PolicyFailure)
    failure = guard(slow)
    assert isinstance(failure, PolicyFailure) and "3 times in a row" in failure.reason
    assert guard(fast) is failure and len(guard.times) == 6  # latched, act not called
    assert guard.times == pytest.approx([0.06, 0.06, 0.01, 0.06, 0.06, 0.06])


class _Plugin:
    """A deploy-side plug-in (loaded as a plug-in is) whose ``act`` advances the runner's
    fake clock by ``delay_s`` (s), or raises."""

    def __init__(self, clock, delay_s: float = 0.0, raises: bool = False) -> None:
        self.clock, self.delay_s, self.raises = clock, delay_s, raises

    def act(self, observation):
        if self.raises:
            raise RuntimeError("boom")
        self.clock.t += self.delay_s
        return np.array([1.0, 0.0], dtype=np.float32)


@pytest.mark.parametrize(
    ("delay_s", "raises", "reason"),
    [
        (
            0.2,
            False,
            "policy error: act took 200 ms, over the 50 ms control period 3 times in a row",
        ),
        (0.0, True, "policy error: RuntimeError: boom"),
    ],
)
def test_deploy_stops_a_raising_or_slow_plugin_as_sim_does(
    delay_s, raises, reason, tmp_path, caplog
):
    from openconvoy.policies.plugin import check_policy_object

    holder: dict = {}

    class Late:
        def act(self, observation):
            return holder["inner"].act(observation)

    policy = check_policy_object(Late(), "late", "test")
    clock, link, runner = follower_setup(tmp_path, policy)
    holder["inner"] = _Plugin(clock, delay_s, raises)
    result = runner.run()
    assert result.policy_errors >= 1
    fired = [r for _, r in result.events]
    assert reason in fired, fired
    assert link.sent[-1][1] == 0.0  # stopped
    meta = json.loads((tmp_path / "vehicle_1.json").read_text())
    assert meta["policy_errors"] == result.policy_errors
    slow = [r.getMessage() for r in caplog.records if "over half the" in r.getMessage()]
    if delay_s:
        assert slow == ["vehicle 1: policy act took 200.0 ms, over half the 50 ms control period"]
        assert meta["policy_act_s"]["max"] == pytest.approx(0.2)
        assert meta["policy_act_s"]["calls"] == 3.0


def test_parallel_api_test_passes_with_a_plugin_policys_member_config():
    from pettingzoo.test import parallel_api_test

    from openconvoy.comms.loss import LossConfig
    from openconvoy.envs import ConvoyEnv
    from tests.pinned_warnings import PETTINGZOO_ALLOWED, pinned

    member = load_policy("tests/data/plugins/equal.toml").member_config
    assert member is not None and len(member.plugins) == 3
    env = ConvoyEnv(member_config=member, loss=LossConfig(per=0.3))
    with pinned(PETTINGZOO_ALLOWED):
        parallel_api_test(env, num_cycles=200)
    assert math.isfinite(env.t)
