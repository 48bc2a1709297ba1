"""The traffic model's batched twins against highway-env's own code, rule by rule, on
random cars (issue 21): IDM's acceleration (``IDMVehicle.acceleration``), the lane-keeping
steering law (``steering_control``) and the closest lane (``get_closest_lane_index``), in
``traffic.jit``'s compiled form and ``traffic.idm``'s numpy form. The whole-road parity
tests (``test_traffic_vector``) hold them only through scenarios."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "highway_env", reason="needs the traffic extra: pip install 'openconvoy[traffic]'"
)

from highway_env.road.road import Road, RoadNetwork  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from openconvoy.envs.traffic import idm as numpy_form  # noqa: E402
from openconvoy.envs.traffic.jit import _idm, _kinematics, _steering, closest_lane  # noqa: E402
from openconvoy.envs.traffic.road import VectorRoad  # noqa: E402
from openconvoy.envs.traffic.state import StraightEdge, TrafficState  # noqa: E402

FAST = settings(max_examples=150, deadline=None)
NET = RoadNetwork.straight_road_network(3, start=0.0, length=1000.0, speed_limit=30.0)
EDGE = StraightEdge.of(NET.graph)
ROAD = VectorRoad(network=NET)
_car = st.tuples(
    st.floats(0.0, 900.0),  # x (m)
    st.integers(0, 2),  # lane
    st.floats(-1.5, 1.5),  # off the lane's centre (m)
    st.floats(-0.4, 0.4),  # heading (rad)
    st.floats(0.0, 40.0),  # speed (m/s)
    st.floats(0.0, 40.0),  # target speed (m/s)
)


def _cars(*cars: tuple) -> tuple[list[IDMVehicle], TrafficState]:
    road = Road(network=NET, np_random=np.random.RandomState(0))
    out = []
    for x, lane, dy, h, v, target in cars:
        y = NET.get_lane(("0", "1", lane)).position(x, dy)[1]
        car = IDMVehicle(road, np.array([x, y]), h, v, target_speed=target)
        car.lane_index = car.target_lane_index = ("0", "1", lane)
        car.lane = NET.get_lane(car.lane_index)
        out.append(car)
    road.vehicles = out
    assert EDGE is not None
    return out, TrafficState(out, EDGE)


@FAST
@given(_car, _car, st.booleans())
def test_idm_is_highway_envs_acceleration(ego: tuple, front: tuple, alone: bool) -> None:
    (a, b), s = _cars(ego, front)
    if not alone and b.position[0] < a.position[0]:
        a, b = b, a  # a front car is ahead
    e, f = (0, 1) if a is s.objs[0] else (1, 0)
    f = -1 if alone else f
    want = a.acceleration(a, None if alone else b)
    s.trig()
    kin = _kinematics(s.x, s.h, s.sp, s.c, s.s, s.lane, s.tspeed, EDGE.limit)
    assert _idm(e, e, f, s.idm_p, kin) == pytest.approx(want, rel=1e-12, abs=1e-12)
    rows = np.array([e])
    got = numpy_form.idm(s, numpy_form.kinematics(s), rows, rows, np.array([f]))[0]
    assert got == pytest.approx(want, rel=1e-12, abs=1e-12)


@FAST
@given(_car, st.integers(0, 2))
def test_steering_is_highway_envs_steering_control(car: tuple, target: int) -> None:
    (a,), s = _cars(car)
    want = a.steering_control(("0", "1", target))
    got = _steering(0, target, s.y, s.h, s.sp, s.params, s.half_len, EDGE.lane_y)
    assert got == pytest.approx(want, rel=1e-12, abs=1e-12)


@FAST
@given(st.floats(-50.0, 1050.0), st.floats(-6.0, 14.0), st.floats(-7.0, 7.0))
def test_closest_lane_is_highway_envs(x: float, y: float, h: float) -> None:
    want = NET.get_closest_lane_index(np.array([x, y]), h)[2]
    assert closest_lane(x, y, h, EDGE.lane_y, EDGE.length) == want
    assert EDGE.closest(np.array([x]), np.array([y]), np.array([h]))[0] == want
    found = ROAD.closest_lane(x, y, h)
    assert found is not None and found[0] == ("0", "1", want) and found[1] is NET.get_lane(found[0])
