"""The convoy in highway-env traffic: world, scenarios, sensing, API (issue 13)."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip(
    "highway_env", reason="needs the traffic extra: pip install 'openconvoy[traffic]'"
)

from highway_env.road.road import Road, RoadNetwork  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402
from pettingzoo.test import parallel_api_test  # noqa: E402

from openconvoy.core import metrics as mt  # noqa: E402
from openconvoy.envs import ConvoyEnv  # noqa: E402
from openconvoy.envs.traffic.env import TRAFFIC_LOG_COLUMNS, TrafficConvoyEnv  # noqa: E402
from openconvoy.envs.traffic.scenarios import HIGHWAY_SCENARIOS, make_highway_scenario  # noqa: E402
from openconvoy.envs.traffic.world import (  # noqa: E402
    TRAFFIC_ID_BASE,
    HighwayFrame,
    TrafficWorld,
    enu_to_highway,
    highway_to_enu,
)
from openconvoy.experiments.runs import RunConfig, run_sim  # noqa: E402
from openconvoy.testing import same

CUT_IN = "highway-cut-in:cut_in_at_s=1,cut_out_at_s=3,duration_s=40,traffic=0"


def test_frame_mapping_is_one_function_and_its_inverse() -> None:
    f = HighwayFrame(300.0, 4.0)
    # ENU north (left of an eastbound car) is highway-env's lower lane index (its -y).
    assert enu_to_highway(f, 10.0, 4.0, 0.3) == (310.0, 0.0, -0.3)
    assert highway_to_enu(f, *enu_to_highway(f, -7.5, 2.5, -1.2)) == pytest.approx(
        (-7.5, 2.5, -1.2)
    )
    # On the road: ENU y = -4 m is the lane to the right of the convoy's.
    world = TrafficWorld(f, [4.8], [1.9], 25.0)
    world.reset(Road(RoadNetwork.straight_road_network(3, length=2000.0)), [])
    world.place([0.0], [-4.0], [0.0], [20.0])
    assert world.convoy[0].lane_index[2] == 2
    world.place([0.0], [0.0], [0.1], [20.0])
    assert world.convoy[0].lane_index[2] == 1
    assert world.convoy[0].heading == pytest.approx(-0.1)


def _world_with_car_behind(gap_m: float) -> tuple[TrafficWorld, IDMVehicle]:
    road = Road(
        RoadNetwork.straight_road_network(3, length=2000.0), np_random=np.random.RandomState(0)
    )
    lane = road.network.get_lane(("0", "1", 1))
    car = IDMVehicle(road, lane.position(300.0 - gap_m, 0.0), 0.0, 25.0, target_speed=25.0)
    world = TrafficWorld(HighwayFrame(300.0, 4.0), [4.8], [1.9], 25.0)
    world.reset(road, [car])
    return world, car


def test_traffic_reacts_to_a_convoy_vehicle_and_sees_collisions() -> None:
    world, car = _world_with_car_behind(20.0)
    # Our vehicle stopped in the lane: the IDM car behind brakes hard for it.
    world.place([0.0], [0.0], [0.0], [0.0])
    world.act(0.0)
    assert car.action["acceleration"] < -5.0
    # The rear sensor view of the convoy vehicle sees nothing ahead of it.
    assert world.in_path() == [None]
    # A car overlapping our vehicle is a collision in highway-env's check.
    world, car = _world_with_car_behind(3.0)
    world.place([0.0], [0.0], [0.0], [25.0])
    world.act(0.0)
    world.step(0.05)
    assert world.traffic_hits() == [True] and car.crashed


def test_ranging_sees_traffic_in_the_path_only() -> None:
    road = Road(RoadNetwork.straight_road_network(3, length=2000.0))
    ahead = IDMVehicle(road, np.array([330.0, 4.0]), 0.0, 20.0)
    beside = IDMVehicle(road, np.array([310.0, 0.0]), 0.0, 20.0)
    world = TrafficWorld(HighwayFrame(300.0, 4.0), [4.8], [1.9], 25.0)
    world.reset(road, [beside, ahead])
    world.place([0.0], [0.0], [0.0], [25.0])
    (seen,) = world.in_path()
    assert seen.is_traffic and seen.target_id == TRAFFIC_ID_BASE + 1
    assert seen.range_m == pytest.approx(30.0)
    assert seen.range_rate_mps == pytest.approx(-5.0)
    assert seen.length_m == 5.0


@pytest.mark.parametrize("spec", HIGHWAY_SCENARIOS)
def test_parallel_api(spec: str) -> None:
    from tests.pinned_warnings import PETTINGZOO_ALLOWED, pinned

    with pinned(PETTINGZOO_ALLOWED):
        parallel_api_test(TrafficConvoyEnv(f"{spec}:traffic=3,duration_s=3"), num_cycles=60)


def test_aec_api_and_single_agent_id() -> None:
    import gymnasium
    from gymnasium.utils.env_checker import check_env
    from pettingzoo.test import api_test

    import openconvoy.envs

    api_test(ConvoyEnv.aec(scenario="highway-cut-in:traffic=3,duration_s=2"), num_cycles=40)
    env = gymnasium.make(openconvoy.envs.HIGHWAY_SINGLE_AGENT_ID, max_time_s=2.0)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=1)
    assert obs.shape == env.observation_space.shape and info["desired_gap_m"] == pytest.approx(21.8)


def test_convoy_env_with_a_highway_spec_is_the_traffic_env() -> None:
    env = ConvoyEnv("highway-slow-traffic", n_followers=3)
    assert isinstance(env, TrafficConvoyEnv)
    assert env.possible_agents == ["follower_1", "follower_2", "follower_3"]
    assert env.presets[0].name == "full-size" and env.presets[1].ranging.max_range_m == 150.0
    with pytest.raises(ValueError, match="cut_in_gap must be 1..2"):
        make_highway_scenario("highway-cut-in:cut_in_gap=3")
    with pytest.raises(ValueError, match="bad parameter 'speed=3'"):
        make_highway_scenario("highway-cut-in:speed=3")


def _rollout(spec: str, seed: int) -> list:
    env = TrafficConvoyEnv(spec)
    rng = np.random.default_rng(1)
    obs, infos = env.reset(seed=seed)
    trace = [(obs, infos, env.world.traffic_states_enu())]
    while env.agents:
        actions = {a: np.array([25.0 + rng.normal(), 0.0], dtype=np.float32) for a in env.agents}
        obs, rew, term, trunc, infos = env.step(actions)
        trace.append((obs, rew, infos, env.world.traffic_states_enu(), env.log_rows()))
    return trace


@pytest.mark.parametrize("spec", HIGHWAY_SCENARIOS)
def test_whole_episode_determinism(spec: str) -> None:
    a = _rollout(f"{spec}:duration_s=1.5,traffic=4", seed=5)
    b = _rollout(f"{spec}:duration_s=1.5,traffic=4", seed=5)
    assert len(a) == len(b) > 10 and same(a, b)
    # Traffic is randomized by the seed.
    c = _rollout(f"{spec}:duration_s=1.5,traffic=4", seed=6)
    assert not np.array_equal(a[0][2], c[0][2])


@pytest.mark.parametrize("spec", ["highway-cut-in:traffic=10", "highway-slow-traffic:traffic=10"])
def test_faster_traffic_paths_match_highway_env_road(spec: str) -> None:
    """The faster traffic paths give highway-env's trajectories: ``fast`` bit for bit,
    ``vector`` (compiled) within 1e-9 m (bit for bit here; compiled code may round the last bits
    differently elsewhere)."""
    ref = _rollout(f"{spec},duration_s=3,road=highway-env", seed=3)
    fast = _rollout(f"{spec},duration_s=3,road=fast", seed=3)
    vector = _rollout(f"{spec},duration_s=3,road=vector", seed=3)
    assert len(fast) == len(ref) == len(vector) > 50
    traffic = lambda entry: entry[2] if len(entry) == 3 else entry[3]  # noqa: E731
    worst = 0.0
    for r, f, v in zip(ref, fast, vector):
        assert np.array_equal(traffic(f), traffic(r))
        worst = max(worst, float(np.max(np.abs(traffic(v) - traffic(r)))))
    assert worst < 1e-9
    # Traffic moved and changed lanes: the test compares something.
    start, end = ref[0][2], ref[-1][3]
    assert np.all(end[:, 0] - start[:, 0] > 30.0)
    assert np.any(np.abs(end[:, 1] - start[:, 1]) > 2.0)


def _cut_in(policy: str, seed: int = 0):
    return run_sim(RunConfig(scenario=CUT_IN, policy=policy, seed=seed))


def test_cut_in_closer_than_braking_allows_stops_follower_1() -> None:
    """The intruder changes in about 6 m ahead of follower 1 at 25 m/s: were it to brake
    at its limit, follower 1 (0.15 s delay, 8 m/s²) would hit it. The rule assumes the
    vehicle ahead may brake (issue 22) and stops follower 1 the tick its ranging sensor
    sees the intruder. (Before, the rule took the closing speed only, and the ladder's
    ranging ACC let follower 1 drive on 6 m behind it.)"""
    r = _cut_in("cacc-allpred+ladder")
    log, m = r.log, r.metrics
    f1 = log["vehicle_id"] == 1
    intruded = f1 & (log["ahead_traffic"] == 1.0)
    t_in = log["t_s"][intruded]
    assert 1.0 < t_in.min() < 1.6 and 3.0 < t_in.max() < 3.8
    assert set(log["mode"][intruded]) == {"failsafe"}
    ((t, vid, why),) = [(e["t_s"], e["vehicle_id"], e["reason"]) for e in r.events]
    assert vid == 1 and t == pytest.approx(t_in.min()) and why.startswith("emergency stop")
    assert m["traffic_collisions"] == 0 and m["collisions"] == 0
    assert 5.0 < m["min_gap_ahead_m"] < 11.0 and not m["gap_restored"]
    # Follower 2 never saw the intruder.
    assert not ((log["vehicle_id"] == 2) & (log["ahead_traffic"] == 1.0)).any()


def _run_env(env: TrafficConvoyEnv, policy: str) -> dict:
    from openconvoy.experiments.runs import rows_to_log
    from openconvoy.policies import load_policy

    pols = {a: load_policy(policy) for a in env.possible_agents}
    obs, _ = env.reset(seed=0)
    rows = []
    while env.agents:
        obs, *_ = env.step({a: pols[a].act(obs[a]) for a in env.agents})
        rows += env.log_rows()
    rows += env.final_log_rows()
    log = rows_to_log(rows)
    return {**mt.traffic_metrics(log, env.vehicle_lengths), "t_end": env.t, "log": log}


def test_cut_in_without_the_ladder_ends_in_an_emergency_stop_or_a_crash() -> None:
    from openconvoy.policies import load_policy

    member = load_policy("cacc-allpred").member_config
    # Cooperative control alone trusts V2V and closes on the car it cannot hear: the
    # braking-aware emergency stop fires, and follower 1 stays stopped on the highway.
    env = TrafficConvoyEnv(CUT_IN, member_config=member, max_time_s=12.0)
    m = _run_env(env, "cacc-allpred")
    assert m["traffic_collisions"] == 0 and not m["gap_restored"]
    assert [e[1] for e in env.safety_events] == [1] and "emergency stop" in env.safety_events[0][2]
    assert env.plant.speed[1] == pytest.approx(0.0, abs=0.01) and 0.5 < m["min_ttc_s"] < 2.5
    # Without that last resort it drives into the intruder.
    env = TrafficConvoyEnv(CUT_IN, member_config=member, emergency_stop=False)
    m = _run_env(env, "cacc-allpred")
    assert m["traffic_collisions"] == 1 and m["min_ttc_s"] < 0.5 and m["t_end"] < 5.0


def test_slow_traffic_leader_follows_it_by_idm() -> None:
    from openconvoy.policies import load_policy

    policy = load_policy("cacc-allpred+ladder")
    env = TrafficConvoyEnv(
        "highway-slow-traffic:duration_s=20,slow_ahead_m=80,traffic=4",
        member_config=policy.member_config,
    )
    pols = {a: load_policy("cacc-allpred+ladder") for a in env.possible_agents}
    obs, _ = env.reset(seed=1)
    while env.agents:
        obs, _, term, _, infos = env.step({a: pols[a].act(obs[a]) for a in env.agents})
    assert not any(term.values())
    lead = env.world.convoy[0]
    # The leader slowed from 25 m/s to the traffic's 15 m/s, an IDM distance behind it.
    assert abs(env.plant.speed[0] - 15.0) < 1.0
    ahead = env.sim.in_path[0]
    assert ahead.is_traffic and 25.0 < ahead.range_m < 45.0
    assert lead.lane_index[2] == 1
    # The followers kept their cooperative gaps behind a slowing leader.
    for a in env.possible_agents:
        assert abs(infos[a]["gap_m"] - infos[a]["desired_gap_m"]) < 2.0


@pytest.mark.parametrize("spec", ["highway-merge:traffic=0", "highway-lane-drop:traffic=3"])
def test_merging_car_joins_the_convoy_lane_ahead_of_the_leader(spec: str) -> None:
    r = run_sim(RunConfig(scenario=f"{spec},duration_s=12", policy="cacc-allpred+ladder", seed=2))
    m, log = r.metrics, r.log
    assert m["traffic_collisions"] == 0 and m["collisions"] == 0
    assert m["duration_s"] == pytest.approx(12.0)
    assert all(c in r.log for c in TRAFFIC_LOG_COLUMNS)
    # By the end the car from the ramp (the ending lane) drives in front of the leader,
    # which follows it by IDM; nothing cut into the convoy's gaps.
    lead_end = (log["vehicle_id"] == 0) & (log["t_s"] == log["t_s"].max())
    assert log["ahead_traffic"][lead_end] == [1.0]
    assert 30.0 < log["ahead_gap_m"][lead_end][0] < 100.0
    assert not ((log["vehicle_id"] > 0) & (log["ahead_traffic"] == 1.0)).any()
    assert math.isnan(m["gap_restore_time_s"]) and m["gap_restored"] is None


def test_render_rgb_array_draws_road_traffic_and_convoy() -> None:
    env = TrafficConvoyEnv("highway-cut-in:traffic=4", render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.shape == (100, 900, 3) and img.dtype == np.uint8
    # The leader's colour and a coop follower's colour are in the picture.
    flat = img.reshape(-1, 3)
    for colour in ((30, 90, 200), (40, 160, 60)):
        assert (flat == colour).all(axis=1).sum() > 50


def test_metrics_json_has_the_traffic_metrics(tmp_path) -> None:
    from openconvoy.cli import main

    out = tmp_path / "run"
    assert (
        main(
            [
                "sim",
                "--scenario",
                "highway-cut-in:duration_s=2,traffic=2",
                "--policy",
                "cacc-allpred+ladder",
                "--out",
                str(out),
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )
    import json

    data = json.loads((out / "metrics.json").read_text())
    for k in mt.TRAFFIC_METRIC_KEYS:
        assert k in data
    log_head = (out / "log.csv").read_text().splitlines()[0].split(",")
    assert log_head[-len(TRAFFIC_LOG_COLUMNS) :] == list(TRAFFIC_LOG_COLUMNS)
    # report recomputes the same traffic metrics from the log alone.
    assert main(["report", str(out), "--out", str(tmp_path / "again.json")]) == 0
    again = json.loads((tmp_path / "again.json").read_text())
    assert {k: again[k] for k in mt.TRAFFIC_METRIC_KEYS} == {
        k: data[k] for k in mt.TRAFFIC_METRIC_KEYS
    }
