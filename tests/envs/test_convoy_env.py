"""ConvoyEnv behaviour: spaces, infos, log rows, termination, truncation, noise, ranging."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openconvoy.comms.geodesy import geodetic_to_enu
from openconvoy.comms.loss import LossConfig
from openconvoy.core.member import MemberConfig
from openconvoy.envs import ConvoyEnv
from openconvoy.envs.convoy_env import INFO_KEYS
from openconvoy.envs.reward import RewardConfig, reward
from openconvoy.envs.vehicles import VEHICLE_PRESETS
from openconvoy.logs import COLUMNS, LogWriter, read_log
from tests.python_world import python_world  # noqa: F401 - reads the Python world


def _hold(env: ConvoyEnv, speed: float = 0.0) -> dict[str, np.ndarray]:
    return {a: np.array([speed, 0.0], dtype=np.float32) for a in env.agents}


def test_default_is_the_paper_scenario() -> None:
    env = ConvoyEnv()
    assert env.scenario.name == "paper"
    assert env.possible_agents == ["follower_1", "follower_2"]
    assert env.dt == pytest.approx(0.05) and env.max_steps == 1200
    space = env.action_space("follower_1")
    assert space.low.tolist() == [0.0, pytest.approx(-math.pi / 2)]
    assert space.high.tolist() == [5.0, pytest.approx(math.pi / 2)]
    assert env.observation_space("follower_2").shape == (env.member_config.layout.size,)
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(infos) == {"follower_1", "follower_2"}
    assert tuple(infos["follower_1"]) == INFO_KEYS
    assert infos["follower_1"]["gap_m"] == pytest.approx(15.0)
    assert infos["follower_1"]["desired_gap_m"] == pytest.approx(15.0)
    assert infos["follower_2"]["cmd_speed_mps"] is None  # nothing commanded yet


def test_infos_count_messages_and_ages() -> None:
    env = ConvoyEnv(max_time_s=2.0)
    env.reset(seed=0)
    while env.agents:
        _, _, _, _, infos = env.step(_hold(env, 0.0))
    info = infos["follower_2"]
    # 2 s of periodic 0.1 s broadcasts at t = 0, 0.1, ..., 2.0: 21 per vehicle.
    assert info["msgs_sent"] == 21
    assert info["msgs_received"] == 2 * 21  # from the leader and follower_1
    assert info["msgs_kept"] == 2 * 21  # all-predecessors keeps both
    assert infos["follower_1"]["msgs_kept"] == 21  # ... but not its follower's
    assert infos["follower_1"]["msgs_received"] == 42
    assert info["msgs_lost"] == 0
    assert info["pred_msg_age_s"] == pytest.approx(0.0)
    assert env.delivery_ratio == 1.0


def test_standing_followers_and_moving_leader_give_growing_errors_and_rewards() -> None:
    env = ConvoyEnv(max_time_s=5.0)
    env.reset(seed=0)
    first = None
    while env.agents:
        _, rewards, _, _, infos = env.step(_hold(env))
        first = first or rewards
    err = infos["follower_1"]["platooning_error_m"]
    assert err == pytest.approx(infos["follower_1"]["gap_m"] - 15.0)
    assert err > 3.0
    assert rewards["follower_1"] < first["follower_1"]
    assert infos["follower_2"]["platooning_error_m"] == pytest.approx(0.0, abs=1e-9)


def test_reward_formula() -> None:
    c = RewardConfig()
    r = reward(
        c,
        [2.5, float("nan"), 100.0],
        [0.5, 0.0, 0.0],
        [5.0, 0.0, 0.0],
        [0.0, 0.785, 0.0],
        [False, False, True],
    )
    assert r[0] == pytest.approx(-(0.5 + 0.05 * 0.25 + 0.01 * 1.0))
    assert r[1] == pytest.approx(-0.02)
    assert r[2] == pytest.approx(-(1.0 + 100.0))  # the spacing term saturates


def test_collision_terminates_everybody() -> None:
    env = ConvoyEnv(max_time_s=60.0, emergency_stop=False)  # (it would stop follower_2 in time)
    env.reset(seed=0)
    steps = 0
    while env.agents:
        # follower_1 stands; follower_2 drives into it at 3 m/s.
        actions = {
            "follower_1": np.array([0.0, 0.0], np.float32),
            "follower_2": np.array([3.0, 0.0], np.float32),
        }
        _, rewards, terms, truncs, infos = env.step(actions)
        steps += 1
    assert terms == {"follower_1": True, "follower_2": True}
    assert truncs == {"follower_1": False, "follower_2": False}
    assert infos["follower_2"]["collision"] and not infos["follower_1"]["collision"]
    half_lengths = 0.5 * (VEHICLE_PRESETS["1/6"].length_m + VEHICLE_PRESETS["1/10"].length_m)
    assert infos["follower_2"]["gap_m"] < half_lengths
    assert rewards["follower_2"] < -100.0
    assert steps < 200
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_truncation_at_max_time() -> None:
    env = ConvoyEnv(max_time_s=1.0)
    env.reset(seed=0)
    steps = 0
    while env.agents:
        _, _, terms, truncs, _ = env.step(_hold(env))
        steps += 1
    assert steps == 20 and all(truncs.values()) and not any(terms.values())
    assert env.t == pytest.approx(1.0)


def test_actions_are_clipped_to_the_space_and_heading_change_is_relative() -> None:
    env = ConvoyEnv(max_time_s=3.0)
    env.reset(seed=0)
    while env.agents:
        _, _, _, _, infos = env.step({a: np.array([99.0, 0.3], np.float32) for a in env.agents})
    assert infos["follower_1"]["cmd_speed_mps"] == pytest.approx(5.0)
    # Turned left: heading grows while moving, y grows.
    assert env.plant.heading[1] > 0.3 and env.plant.y[1] > 0.0


def test_log_rows_have_the_design_columns_and_geodesy(tmp_path) -> None:
    env = ConvoyEnv(loss=LossConfig(per=0.5), max_time_s=2.0)
    env.reset(seed=1)
    assert env.log_rows() == []  # a row needs the tick's command
    with LogWriter(tmp_path / "log.csv") as log:
        while env.agents:
            before = (float(env.plant.x[1]), float(env.plant.speed[1]), env.t)
            env.step(_hold(env, 1.0))
            rows = env.log_rows()
            log.write_many(rows)
    assert [tuple(r) for r in rows] == [COLUMNS] * 3
    data = read_log(tmp_path / "log.csv")
    assert len(data["t_s"]) == 3 * 40
    assert math.isnan(data["gap_m"][0]) and data["t_s"][0] == 0.0
    last = rows
    # A row is the state at its tick and the command computed from it (as on vehicles).
    assert (last[1]["x_m"], last[1]["speed_mps"], last[1]["t_s"]) == pytest.approx(before)
    assert [r["vehicle_id"] for r in last] == [0, 1, 2]
    assert last[1]["cmd_speed_mps"] == pytest.approx(1.0)
    assert last[1]["gap_m"] == pytest.approx(
        math.hypot(last[0]["x_m"] - last[1]["x_m"], last[0]["y_m"] - last[1]["y_m"])
    )
    assert last[2]["mode"] == "coop" and last[0]["mode"] == "coop"
    final = env.final_log_rows()  # the state the episode ended in, without a command
    assert final[1]["t_s"] == pytest.approx(2.0) and math.isnan(final[1]["cmd_speed_mps"])
    assert final[1]["x_m"] == pytest.approx(float(env.plant.x[1]))
    # lat/lon round-trip to the ENU position around the scenario's origin.
    x, y, _ = geodetic_to_enu(env.scenario.origin, last[2]["lat_deg"], last[2]["lon_deg"])
    assert (x, y) == (
        pytest.approx(last[2]["x_m"], abs=1e-6),
        pytest.approx(last[2]["y_m"], abs=1e-6),
    )
    # Loss shows in the counters: received + lost = what the others sent to this vehicle.
    sent_by_others = sum(r["msgs_sent"] for r in last if r["vehicle_id"] != 1)
    assert last[1]["msgs_received"] + last[1]["msgs_lost"] == sent_by_others
    assert last[1]["msgs_lost"] > 0


def test_gps_noise_moves_what_members_see_not_the_truth() -> None:
    exact = ConvoyEnv(max_time_s=1.0)
    noisy = ConvoyEnv(max_time_s=1.0, gps_noise_m=0.5)
    o_exact, _ = exact.reset(seed=0)
    o_noisy, i_noisy = noisy.reset(seed=0)
    assert i_noisy["follower_1"]["gap_m"] == pytest.approx(15.0)  # ground truth
    lay = exact.member_config.layout
    pred = lay.view(o_exact["follower_1"]).states("pred_1")[0]
    pred_noisy = lay.view(o_noisy["follower_1"]).states("pred_1")[0]
    assert pred[0] == pytest.approx(15.0)
    assert pred_noisy[0] != pytest.approx(15.0, abs=1e-3)
    assert abs(pred_noisy[0] - 15.0) < 5 * 0.5 * math.sqrt(2)


def _degraded_run(presets) -> tuple[set, list[float]]:
    ladder_cfg = MemberConfig().ladder.__class__(
        enabled=True, degrade_after_s=0.3, stop_after_s=30.0
    )
    cfg = MemberConfig(ladder=ladder_cfg)
    # Every message arrives 1 s late: older than degrade_after_s, so the ladder degrades.
    env = ConvoyEnv(
        member_config=cfg, vehicle_presets=presets, loss=LossConfig(latency_s=1.0), max_time_s=4.0
    )
    env.reset(seed=0)
    modes, cmds = set(), []
    while env.agents:
        _, _, _, _, infos = env.step(_hold(env, 1.0))
        modes.add(infos["follower_1"]["mode"])
        cmds.append(infos["follower_1"]["cmd_speed_mps"])
    return modes, cmds


def test_ranging_sensor_reading_reaches_the_ladder() -> None:
    with_sensor, cmd_sensor = _degraded_run(["1/10", VEHICLE_PRESETS["1/6"].with_ranging(), "1/10"])
    without, cmd_plain = _degraded_run(["1/10", "1/6", "1/10"])
    # Nothing heard for the first second (stop), then degraded on 1 s old messages.
    assert with_sensor == without == {"stop", "degraded"}
    # In degraded mode the ACC law uses the sensor's fresh, noisy range instead of the
    # estimate from stale messages: the commands differ.
    late = slice(30, None)
    assert not np.allclose(cmd_sensor[late], cmd_plain[late])
    assert all(c >= 0.0 for c in cmd_sensor)


def test_vehicle_presets_override_sets_the_convoy() -> None:
    env = ConvoyEnv("emergency-braking", vehicle_presets=["full-size"] * 5)
    assert env.possible_agents == [f"follower_{i}" for i in range(1, 5)]
    assert env.action_space("follower_4").high[0] == pytest.approx(40.0)
    with pytest.raises(ValueError, match="n_followers=2 but 5 vehicle presets"):
        ConvoyEnv("paper", n_followers=2, vehicle_presets=["1/10"] * 5)


def test_long_convoy_runs() -> None:
    env = ConvoyEnv(n_followers=100, loss=LossConfig(per=0.2), max_time_s=0.5)
    obs, _ = env.reset(seed=0)
    assert len(obs) == 100
    while env.agents:
        env.step(_hold(env, 0.5))
    assert 0.7 < env.delivery_ratio < 0.9


@pytest.mark.parametrize(
    "bad", [{"control_rate_hz": 0.0}, {"gps_noise_m": -1.0}, {"render_mode": "human"}]
)
def test_bad_arguments_are_named(bad) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        ConvoyEnv(**bad)


def test_event_trigger_sends_less_than_periodic_at_steady_speed() -> None:
    from openconvoy.core.gates import TriggerConfig

    counts = {}
    for kind in ("periodic", "event"):
        trigger = TriggerConfig(
            kind=kind, period_s=0.1, threshold_m=0.25, speed_threshold_mps=0.2, max_silence_s=1.0
        )
        env = ConvoyEnv(member_config=MemberConfig(trigger=trigger), max_time_s=10.0)
        env.reset(seed=0)
        while env.agents:
            _, _, _, _, infos = env.step(_hold(env, 0.0))
        counts[kind] = infos["follower_2"]["msgs_sent"]
    assert counts["periodic"] == 101
    # Standing still: only the max-silence heartbeats (about one per second) go out.
    assert 9 <= counts["event"] <= 12
    assert ConvoyEnv().vehicle_lengths == {0: 0.779, 1: 0.97, 2: 0.779}


def test_reset_leaves_the_garbage_collector_as_it_found_it() -> None:
    """The first sense runs with collection paused (``envs.world``); it comes back on,
    and stays off for a caller who turned it off."""
    import gc

    env = ConvoyEnv("paper", n_followers=30, backend="python")
    assert gc.isenabled()
    env.reset(seed=0)
    assert gc.isenabled()
    gc.disable()
    try:
        env.reset(seed=1)
        assert not gc.isenabled()
    finally:
        gc.enable()
    # All 30 followers heard every predecessor at t = 0 (the paused block did its work).
    assert [len(m.buffer.heard()) for m in env.members[1:]] == list(range(1, 31))


def test_without_numba_auto_is_the_python_path(monkeypatch) -> None:
    """The vehicle runtime needs no numba: ``auto`` falls back, ``compiled`` says why."""
    import openconvoy.envs.convoy_env as convoy_env_mod
    from openconvoy.core.errors import ConfigError
    from openconvoy.envs.compiled import BACKEND_ENV_VAR

    def no_numba(*args, **kwargs):
        raise ImportError("No module named 'numba'")

    monkeypatch.setattr(convoy_env_mod, "CompiledConvoy", no_numba)
    monkeypatch.setenv(BACKEND_ENV_VAR, "auto")
    env = ConvoyEnv(loss=0.2)
    assert env.backend == "python"
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"follower_1", "follower_2"} and env.sim.n_vehicles == 3
    with pytest.raises(ConfigError, match="numba"):
        ConvoyEnv(backend="compiled")


def test_a_heading_bias_is_what_members_see_and_the_vehicle_steers_by() -> None:
    """A leader whose autopilot believes its heading 0.1 rad left of the truth: it reports
    and broadcasts the believed heading, and steering the road by it, it drives its true
    heading off the road and its track drifts (the PX4 demo's followers: 2-3 m)."""
    import dataclasses

    from openconvoy.envs.vehicles import vehicle_preset

    biased = dataclasses.replace(vehicle_preset("1/10"), heading_bias_rad=0.1)
    env = ConvoyEnv("paper", n_followers=1, plant_presets=[biased, "1/10"])
    env.reset(seed=0)
    still = {a: np.zeros(2, dtype=np.float32) for a in env.agents}
    ys = []
    for _ in range(200):  # 10 s
        env.step(still)
        ys.append(env.sim.truth.y[0])
    own = env.sim.members[0].own
    assert own is not None
    assert own.heading == pytest.approx(env.sim.truth.heading[0] + 0.1)
    assert max(abs(y) for y in ys) > 0.05  # the unbiased leader stays on the road
    straight = ConvoyEnv("paper", n_followers=1)
    straight.reset(seed=0)
    for _ in range(200):
        straight.step(still)
    assert abs(straight.sim.truth.y[0]) < 0.01
    from openconvoy.envs import VectorConvoyEnv

    with pytest.raises(ValueError, match="heading bias"):
        VectorConvoyEnv(1, vehicle_presets=[biased, "1/10"], n_followers=1)


def test_a_heading_bias_moves_the_vehicle_faster_than_it_reports() -> None:
    """A follower whose autopilot believes its heading 9.6 degrees off (the PX4 demo's
    follower 1): its speed is reported as its velocity projected on that heading, so at a
    reported 1 m/s it moves 1 / cos(9.6 degrees) = 1.0142 m/s along its track; its own
    state and its messages carry the reported speed."""
    import dataclasses

    from openconvoy.envs.vehicles import vehicle_preset

    bias = math.radians(-9.6)
    biased = dataclasses.replace(vehicle_preset("1/10"), heading_bias_rad=bias)
    env = ConvoyEnv("paper", n_followers=2, plant_presets=["1/10", biased, "1/10"])
    env.reset(seed=0)
    drive = {a: np.array([1.0, 0.0], dtype=np.float32) for a in env.agents}
    for _ in range(300):  # 15 s: at 1 m/s, back on the road
        env.step(drive)
    x0, y0, t0 = env.sim.truth.x[1], env.sim.truth.y[1], env.sim.t
    for _ in range(40):
        env.step(drive)
    reported = env.sim.truth.speed[1]
    assert reported == pytest.approx(1.0, abs=0.01)
    moved = math.hypot(env.sim.truth.x[1] - x0, env.sim.truth.y[1] - y0) / (env.sim.t - t0)
    assert moved == pytest.approx(reported / math.cos(bias), abs=0.002)
    assert env.sim.members[1].own.speed == pytest.approx(reported)
