"""VectorRoad: traffic state in arrays, highway-env's objects kept as its public face."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "highway_env", reason="needs the traffic extra: pip install 'openconvoy[traffic]'"
)

from highway_env.road.road import Road, RoadNetwork  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402

from openconvoy.envs.traffic.road import VectorRoad  # noqa: E402
from openconvoy.envs.traffic.world import HighwayFrame, ScriptedLaneChanger, TrafficWorld  # noqa: E402

DT = 0.05
# Both ways of running VectorRoad's tick: numba's kernels and numpy calls.
COMPILED = pytest.mark.parametrize("compiled", [True, False], ids=["numba", "numpy"])


def _road(road_cls: type, net: RoadNetwork, compiled: bool) -> Road:
    road = road_cls(network=net, np_random=np.random.RandomState(0))
    if isinstance(road, VectorRoad) and not compiled:
        road.compiled = False  # (compiled: the default where numba is installed)
    return road


def _world(road_cls: type, length_m: float, compiled: bool = True) -> TrafficWorld:
    """Twelve IDM/MOBIL cars at mixed speeds on three lanes, a convoy car among them."""
    net = RoadNetwork.straight_road_network(3, start=0.0, length=length_m, speed_limit=40.0)
    road = _road(road_cls, net, compiled)
    rs = np.random.RandomState(7)
    cars = []
    for k in range(12):
        lane = net.get_lane(("0", "1", k % 3))
        speed = float(rs.uniform(18.0, 30.0))
        cars.append(
            IDMVehicle(
                road, lane.position(30.0 + 14.0 * k, 0.0), 0.0, speed, target_speed=speed + 3
            )
        )
    world = TrafficWorld(HighwayFrame(100.0, 4.0), [4.8], [1.9], 25.0)
    world.reset(road, cars)
    return world


def _drive(world: TrafficWorld, ticks: int) -> np.ndarray:
    """Traffic states (ENU rows) per tick; at tick 20 a caller slows car 4 through its
    highway-env object (what a user of the objects may do)."""
    out = []
    for k in range(ticks):
        world.place([22.0 * DT * k], [0.0], [0.0], [22.0])
        if k:
            world.step(DT)
        if k == 20:
            world.traffic[4].speed = 8.0
        world.act(DT * k)
        out.append(world.traffic_states_enu())
    return np.array(out)


@COMPILED
def test_vector_road_gives_highway_env_trajectories_through_object_edits_and_lane_end(
    compiled: bool,
) -> None:
    # 600 m of road: cars pass its end mid-run, where VectorRoad hands over to highway-env.
    ref = _drive(_world(Road, 600.0), 320)
    world = _world(VectorRoad, 600.0, compiled)
    road = world.road
    assert isinstance(road, VectorRoad) and road.vector_state(world._all) is not None
    vec = _drive(world, 320)
    assert np.max(np.abs(vec - ref)) < 1e-9
    # The run changed lanes, braked for the edit and drove past the lane's end.
    assert np.any(np.abs(ref[-1, :, 1] - ref[0, :, 1]) > 2.0)
    assert ref[21, 4, 3] < 10.0
    assert np.max(ref[-1, :, 0]) + 100.0 > 600.0


def _dense_world(road_cls: type, compiled: bool, seed: int = 13) -> TrafficWorld:
    """Dense random traffic on 2-4 lanes: IDM cars with random politeness, delta, lane-change
    delay and gain (some without lane changes), scripted cars, two convoy cars driving
    into it: crashes, lane-change aborts and polite MOBIL changes all happen."""
    rs = np.random.RandomState(seed)
    lanes = rs.randint(2, 5)
    limit = float(rs.uniform(25, 40))
    net = RoadNetwork.straight_road_network(lanes, start=0.0, length=3000.0, speed_limit=limit)
    road = _road(road_cls, net, compiled)
    cars: list = []
    for k in range(rs.randint(5, 40)):
        lane = net.get_lane(("0", "1", int(rs.randint(lanes))))
        speed = float(rs.uniform(5.0, 35.0))
        pos = lane.position(20.0 + 9.0 * k + rs.uniform(0, 3), rs.uniform(-0.5, 0.5))
        if rs.rand() < 0.1:
            when, to, v = rs.uniform(0, 5), int(rs.randint(lanes)), float(rs.uniform(10, 30))
            cars.append(ScriptedLaneChanger(road, pos, 0.0, speed, [(when, to, v)], speed))
            continue
        heading, target = float(rs.uniform(-0.05, 0.05)), float(rs.uniform(10, 40))
        car = IDMVehicle(road, pos, heading, speed, target_speed=target)
        car.enable_lane_change = bool(rs.rand() < 0.9)
        car.POLITENESS = float(rs.uniform(0, 1)) if rs.rand() < 0.5 else 0.0
        car.DELTA = float(rs.uniform(3.5, 4.5)) if rs.rand() < 0.5 else 4.0
        car.LANE_CHANGE_DELAY = float(rs.uniform(0.3, 1.5))
        car.LANE_CHANGE_MIN_ACC_GAIN = float(rs.uniform(0.0, 0.3))
        cars.append(car)
    world = TrafficWorld(HighwayFrame(100.0, 4.0 * rs.randint(lanes)), [4.8] * 2, [1.9] * 2, 25.0)
    world.reset(road, cars)
    world.speed = rs.uniform(15, 30)  # type: ignore[attr-defined]  # the convoy's, m/s
    return world


def _drive_dense(world: TrafficWorld, ticks: int) -> tuple[np.ndarray, list, list]:
    """Traffic states and targets per tick, then crashes and the convoy's hits and radar."""
    v, out = world.speed, []  # type: ignore[attr-defined]
    for k in range(ticks):
        world.place([100 + v * DT * k, 80 + v * DT * k], [0.0, 0.0], [0.0, 0.0], [v, v])
        if k:
            world.step(DT)
        world.act(DT * k)
        targets = [car.target_lane_index[2] for car in world.traffic] if k % 20 == 0 else []
        out.append(np.concatenate((world.traffic_states_enu().ravel(), targets)))
    radar = [(p.target_id, p.range_m, p.range_rate_mps) if p else None for p in world.in_path()]
    return np.concatenate(out), [c.crashed for c in world.traffic], world.traffic_hits() + radar


@COMPILED
def test_vector_road_matches_highway_env_in_dense_traffic_with_crashes_and_aborts(
    compiled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    events = {"abort": 0, "polite_change": 0}
    policy = IDMVehicle.change_lane_policy

    def counted(car: IDMVehicle) -> None:  # counts what highway-env's own run does
        before, changing = car.target_lane_index, car.lane_index != car.target_lane_index
        policy(car)
        if car.target_lane_index != before:
            key = "abort" if changing else "polite_change" if car.POLITENESS > 0 else "change"
            events[key] = events.get(key, 0) + 1

    monkeypatch.setattr(IDMVehicle, "change_lane_policy", counted)
    ref = _drive_dense(_dense_world(Road, compiled), 200)
    monkeypatch.setattr(IDMVehicle, "change_lane_policy", policy)
    world = _dense_world(VectorRoad, compiled)
    got = _drive_dense(world, 200)
    assert np.max(np.abs(got[0] - ref[0])) < 1e-9
    assert got[1:] == ref[1:]
    # What the run exercised: crashes (cars and a convoy car), aborts, polite changes,
    # a scripted car; and VectorRoad ran the whole run on its arrays.
    assert sum(ref[1]) >= 5 and any(ref[2][:2])
    assert events["abort"] >= 1 and events["polite_change"] >= 3
    assert any(isinstance(car, ScriptedLaneChanger) for car in world.traffic)
    assert isinstance(world.road, VectorRoad) and world.road.known_idm_accel(world.convoy[0])


def test_vector_road_without_numba_logs_one_line_and_runs_the_numpy_code() -> None:
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['numba'] = None\n"
        "from tests.envs.traffic.test_traffic_vector import VectorRoad, _dense_world, _drive_dense\n"
        "w = _dense_world(VectorRoad, True)\n"
        "assert not w.road.compiled and not VectorRoad.compiled\n"
        "_dense_world(VectorRoad, True)\n"  # a second road: no second line
        "print(repr(_drive_dense(w, 60)[0].tolist()))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines() == [
        "traffic road=vector: numba is missing, the traffic runs as numpy calls (~2x slower); "
        "pip install 'openconvoy[traffic]'"
    ]
    compiled = _drive_dense(_dense_world(VectorRoad, True), 60)[0]
    assert np.max(np.abs(np.array(eval(r.stdout)) - compiled)) < 1e-9


def test_objects_read_from_a_vector_road_are_current() -> None:
    world = _world(VectorRoad, 5000.0)
    _drive(world, 30)
    states = world.traffic_states_enu()
    objects = np.array(
        [(v.position[0] - 100.0, 4.0 - v.position[1], v.speed) for v in world.traffic]
    )
    assert np.array_equal(objects, states[:, [0, 1, 3]])
    lead = world.convoy[0]
    assert lead.position[0] == pytest.approx(100.0 + 22.0 * DT * 29) and lead.lane_index[2] == 1


def test_touching_pairs_keeps_every_pair_highway_env_acts_on() -> None:
    """The numpy pre-filter skips a pair only when highway-env's own test
    (``_is_colliding``: intersecting now, or will intersect within dt) finds neither."""
    from highway_env.vehicle.kinematics import Vehicle

    from openconvoy.envs.traffic.world import touching_pairs

    rs = np.random.RandomState(3)
    road = Road(RoadNetwork.straight_road_network(2))
    upper = np.array([[False, True], [False, False]])
    counts = {"acted": 0, "skipped": 0, "kept_idle": 0}
    for _ in range(600):
        a = Vehicle(road, rs.uniform(-3, 3, 2), rs.uniform(-0.8, 0.8), rs.uniform(0, 30))
        offset = np.array([rs.choice([-6.0, 0.0, 6.0]), rs.choice([-4.0, 0.0, 4.0])])
        b = Vehicle(road, rs.uniform(-3, 3, 2) + offset, rs.uniform(-0.8, 0.8), rs.uniform(0, 30))
        h = np.array([a.heading, b.heading])
        kept = touching_pairs(
            np.array([a.position[0], b.position[0]]),
            np.array([a.position[1], b.position[1]]),
            np.cos(h),
            np.sin(h),
            np.array([a.speed, b.speed]),
            np.full((2, 2), 0.5 * (a.diagonal + b.diagonal)),
            0.5 * np.array([(a.LENGTH, a.WIDTH), (b.LENGTH, b.WIDTH)]),
            upper,
            0.5,
        )
        intersecting, will_intersect, _ = a._is_colliding(b, 0.5)
        if intersecting or will_intersect:
            assert kept == [(0, 1)]
            counts["acted"] += 1
        else:
            counts["skipped" if not kept else "kept_idle"] += 1
    # Both outcomes occur, and the filter drops most of the idle pairs.
    assert counts["acted"] > 50 and counts["skipped"] > 5 * counts["kept_idle"]


def _drive_edited(world: TrafficWorld, ticks: int) -> np.ndarray:
    """Traffic states per tick; at tick 20 every car's parameters are edited through its
    highway-env object (highway-env's own ``randomize_behavior``, no lane changes, a lower
    top speed, softer IDM, slower steering, one car lengthened)."""
    out = []
    for k in range(ticks):
        world.place([22.0 * DT * k], [0.0], [0.0], [22.0])
        if k:
            world.step(DT)
        if k == 20:
            for j, car in enumerate(world.traffic):
                (
                    car.randomize_behavior,
                    lambda c=car: setattr(c, "enable_lane_change", False),
                    lambda c=car: setattr(c, "MAX_SPEED", 18.0),
                    lambda c=car: setattr(c, "COMFORT_ACC_MAX", 1.0),
                    lambda c=car: setattr(c, "KP_HEADING", 1.0),
                )[j % 5]()
            car = world.traffic[3]
            car.LENGTH, car.diagonal = 9.0, float(np.hypot(9.0, car.WIDTH))
        world.act(DT * k)
        out.append(world.traffic_states_enu())
    return np.array(out)


@COMPILED
def test_vector_road_reads_parameters_edited_on_the_objects(compiled: bool) -> None:
    ref = _drive_edited(_world(Road, 5000.0), 160)
    got = _drive_edited(_world(VectorRoad, 5000.0, compiled), 160)
    assert np.max(np.abs(got - ref)) < 1e-9
    # The edits changed the run (else this test could not fail).
    plain = _drive(_world(Road, 5000.0), 160)
    assert np.max(np.abs(plain[:, :, :2] - ref[:, :, :2])) > 1.0


@COMPILED
def test_vector_road_with_no_traffic_runs(compiled: bool) -> None:
    """Only convoy vehicles on the road (no car for ``step`` to move)."""
    net = RoadNetwork.straight_road_network(3, start=0.0, length=1000.0, speed_limit=40.0)
    world = TrafficWorld(HighwayFrame(100.0, 4.0), [4.8, 4.8], [1.9, 1.9], 25.0)
    world.reset(_road(VectorRoad, net, compiled), [])
    for k in range(5):
        world.place([10.0 + k, -5.0 + k], [0.0, 0.0], [0.0, 0.0], [20.0, 20.0])
        if k:
            world.step(DT)
        world.act(DT * k)
    assert world.road.vector_state(world._all) is not None
    ahead = world.in_path()[1]
    assert ahead is not None and ahead.target_id == 0 and ahead.range_m == pytest.approx(15.0)
