"""VectorRoad: traffic state in arrays, highway-env's objects kept as its public face."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "highway_env", reason="needs the traffic extra: pip install 'openconvoy[traffic]'"
)

from highway_env.road.road import Road, RoadNetwork  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402

from openconvoy.envs.traffic import HighwayFrame, TrafficWorld  # noqa: E402
from openconvoy.envs.traffic_vector import VectorRoad  # noqa: E402

DT = 0.05


def _world(road_cls: type, length_m: float) -> TrafficWorld:
    """Twelve IDM/MOBIL cars at mixed speeds on three lanes, a convoy car among them."""
    net = RoadNetwork.straight_road_network(3, start=0.0, length=length_m, speed_limit=40.0)
    road = road_cls(network=net, np_random=np.random.RandomState(0))
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


def test_vector_road_gives_highway_env_trajectories_through_object_edits_and_lane_end() -> None:
    # 600 m of road: cars pass its end mid-run, where VectorRoad hands over to highway-env.
    ref = _drive(_world(Road, 600.0), 320)
    world = _world(VectorRoad, 600.0)
    road = world.road
    assert isinstance(road, VectorRoad) and road.vector_state(world._all) is not None
    vec = _drive(world, 320)
    assert np.max(np.abs(vec - ref)) < 1e-9
    # The run changed lanes, braked for the edit and drove past the lane's end.
    assert np.any(np.abs(ref[-1, :, 1] - ref[0, :, 1]) > 2.0)
    assert ref[21, 4, 3] < 10.0
    assert np.max(ref[-1, :, 0]) + 100.0 > 600.0


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

    from openconvoy.envs.traffic import touching_pairs

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
