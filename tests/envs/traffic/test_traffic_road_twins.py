"""``VectorRoad``'s tick, whole and piece by piece, against highway-env's own classes on
random road states (issue 21): ``Road.act`` (``IDMVehicle.act``: MOBIL, aborts, steering,
IDM on the current and target lane), ``Road.step`` (``IDMVehicle.step`` and the
collisions), ``Road.neighbour_vehicles``, ``IDMVehicle.mobil``, ``Vehicle.step`` and
highway-env's ``utils``; ``TrafficWorld.in_path`` on a ``VectorRoad`` against the same
world on highway-env's ``Road``. Both forms of each rule run: ``traffic.jit``'s compiled
one and ``traffic.idm`` / ``traffic.road``'s numpy one.

Exact comparisons: both forms do highway-env's operations in the same order on the same
IEEE doubles (no fastmath). The compiled form is held to 1e-12 relative: its ``math.asin``,
``atan`` and ``tan`` are libm's, one ulp off numpy's own routines (which highway-env calls)
on some inputs; seen here in a heading, a steering angle, an IDM acceleration."""

from __future__ import annotations

import copy

import numpy as np
import pytest

pytest.importorskip(
    "highway_env", reason="needs the traffic extra: pip install 'openconvoy[traffic]'"
)

from highway_env import utils  # noqa: E402
from highway_env.road.road import Road, RoadNetwork  # noqa: E402
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from openconvoy.envs.traffic import road as road_module  # noqa: E402
from openconvoy.envs.traffic.idm import _not_zero as numpy_not_zero  # noqa: E402
from openconvoy.envs.traffic.idm import _steering, neighbours  # noqa: E402
from openconvoy.envs.traffic.jit import (  # noqa: E402
    _apart,
    _clip,
    _front_rear,
    _kinematics,
    _mobil,
    _move,
    _not_zero,
    _on_lanes,
    _wrap_to_pi,
    step,
)
from openconvoy.envs.traffic.road import VectorRoad  # noqa: E402
from openconvoy.envs.traffic.state import StraightEdge, TrafficState  # noqa: E402
from openconvoy.envs.traffic.world import (  # noqa: E402
    HighwayFrame,
    ScriptedLaneChanger,
    TrafficWorld,
)

SOME = settings(max_examples=100, deadline=None)
FAST = settings(max_examples=150, deadline=None)
DT = 0.05
NET = RoadNetwork.straight_road_network(3, start=0.0, length=1000.0, speed_limit=30.0)
EDGE = StraightEdge.of(NET.graph)
assert EDGE is not None

_car = st.fixed_dictionaries(
    {
        "x": st.floats(0.0, 120.0),  # dense: neighbours, MOBIL, aborts and crashes happen
        "lane": st.integers(0, 2),
        "dy": st.floats(-2.5, 2.5),  # off the lane's centre (m)
        "h": st.floats(-0.3, 0.3),  # heading (rad)
        "v": st.floats(0.0, 35.0),  # speed (m/s)
        "target": st.floats(0.0, 40.0),  # target speed (m/s)
        # Weighted so that a tick starts lane changes (MOBIL's timer fired, no change in
        # progress, lane changes on, not crashed) as well as aborting them.
        "tgt": st.sampled_from([0, 0, -1, 1]),  # target lane offset (a change in progress)
        "timer": st.floats(0.0, 2.0),  # s; LANE_CHANGE_DELAY is 1 s
        "lc": st.sampled_from([True, True, False]),  # enable_lane_change
        "crashed": st.sampled_from([False, False, False, True]),
        "scripted": st.sampled_from([False, False, False, True]),  # a ScriptedLaneChanger
        "steer": st.floats(-1.0, 1.0),
        "acc": st.floats(-8.0, 8.0),
    }
)
_cars = st.lists(_car, min_size=1, max_size=9)


def _road(cls: type, cars: list[dict], compiled: bool = True) -> tuple[Road, list[IDMVehicle]]:
    """A ``cls`` road holding ``cars`` as highway-env ``IDMVehicle`` s (or our
    ``ScriptedLaneChanger`` s, an ``IDMVehicle`` holding its speed and lane)."""
    road = cls(network=NET, np_random=np.random.RandomState(0))
    if isinstance(road, VectorRoad):
        road.compiled = compiled
    out = []
    for c in cars:
        lane = NET.get_lane(("0", "1", c["lane"]))
        where = lane.position(c["x"], c["dy"])
        if c["scripted"]:
            car = ScriptedLaneChanger(road, where, c["h"], c["v"], target_speed=c["target"])
        else:
            car = IDMVehicle(
                road, where, c["h"], c["v"], target_speed=c["target"], enable_lane_change=c["lc"]
            )
        car.timer = c["timer"]  # (0.0 would be replaced by highway-env's default)
        car.lane_index = ("0", "1", c["lane"])
        car.lane = NET.get_lane(car.lane_index)
        car.target_lane_index = ("0", "1", int(np.clip(c["lane"] + c["tgt"], 0, 2)))
        car.crashed = c["crashed"]
        car.action = {"steering": c["steer"], "acceleration": c["acc"]}
        out.append(car)
    road.vehicles = out
    return road, out


ULP = {"rel": 1e-12, "abs": 1e-12}


def _same(got: list[tuple], want: list[tuple], compiled: bool) -> None:
    """``_seen`` rows equal: discrete fields exactly, floats exactly for numpy, to
    ``ULP`` for the compiled form (the module doc)."""
    assert len(got) == len(want)
    for g, w in zip(got, want):
        for a, b in zip(g, w):
            if isinstance(b, float) and compiled:
                assert a == pytest.approx(b, **ULP), (g, w)
            else:
                assert a == b, (g, w)


def _seen(cars: list[IDMVehicle]) -> list[tuple]:
    """What a tick decides and moves, per car."""
    return [
        (
            *map(float, c.position),
            float(c.heading),
            float(c.speed),
            c.lane_index,
            c.target_lane_index,
            float(c.timer),
            bool(c.crashed),
            float(c.action["steering"]),
            float(c.action["acceleration"]),
        )
        for c in cars
    ]


@SOME
@given(_cars, st.booleans())
def test_a_tick_is_highway_envs_act_then_step(cars: list[dict], compiled: bool) -> None:
    """``VectorRoad.act`` then ``step`` (``traffic.jit.decide`` / ``step`` compiled, or
    ``traffic.idm.decide`` / ``traffic.road.move`` as numpy) against highway-env's
    ``Road.act`` then ``Road.step`` on the same random cars (IDM with and without MOBIL,
    ``ScriptedLaneChanger``, crashed, mid lane change): every car's decision, state
    after the step, lane, timer and crash; and ``known_idm_accel`` is highway-env's IDM
    on the car's lane, clipped."""
    ref_road, ref = _road(Road, cars)
    vec_road, vec = _road(VectorRoad, cars, compiled)
    assert isinstance(vec_road, VectorRoad) and vec_road.vector_state(vec) is not None
    ref_road.act()
    vec_road.act()
    for car in ref:
        front, _ = ref_road.neighbour_vehicles(car, car.lane_index)
        want = float(np.clip(car.acceleration(car, front), -car.ACC_MAX, car.ACC_MAX))
        got = vec_road.known_idm_accel(vec[ref.index(car)])
        assert got == (pytest.approx(want, **ULP) if compiled else want)
    _same(_seen(vec_road.vehicles), _seen(ref), compiled)
    ref_road.step(DT)
    vec_road.step(DT)
    _same(_seen(vec_road.vehicles), _seen(ref), compiled)


@FAST
@given(_cars, st.data())
def test_neighbours_are_highway_envs(cars: list[dict], data: st.DataObject) -> None:
    """``traffic.jit._front_rear`` (on ``_on_lanes``'s table) and ``traffic.idm.neighbours``
    find ``Road.neighbour_vehicles``'s front and rear car of any car on any lane; the
    table is ``lane.on_lane(position, margin=1)``."""
    road, objs = _road(Road, cars)
    s = TrafficState(objs, EDGE)
    e = data.draw(st.integers(0, len(objs) - 1))
    lane_id = data.draw(st.integers(0, 2))
    front, rear = road.neighbour_vehicles(objs[e], ("0", "1", lane_id))
    want = tuple(-1 if v is None else objs.index(v) for v in (front, rear))
    on = _on_lanes(s.x, s.y, EDGE.geo, EDGE.length, EDGE.vlen)
    for k, car in enumerate(objs):
        for q in range(3):
            assert on[q, k] == NET.get_lane(("0", "1", q)).on_lane(car.position, margin=1)
    assert tuple(_front_rear(lane_id, e, s.x, on)) == want
    got = neighbours(s, np.array([lane_id]), np.array([e]))
    assert (int(got[0][0]), int(got[1][0])) == want


@FAST
@given(_cars, st.data())
def test_mobil_is_highway_envs(cars: list[dict], data: st.DataObject) -> None:
    """``traffic.jit._mobil`` decides as ``IDMVehicle.mobil`` for any car and side lane."""
    road, objs = _road(Road, cars)
    s = TrafficState(objs, EDGE)
    k = data.draw(st.integers(0, len(objs) - 1))
    side = data.draw(st.sampled_from([q for q in (s.lane[k] - 1, s.lane[k] + 1) if 0 <= q < 3]))
    want = objs[k].mobil(("0", "1", int(side)))
    kin = _kinematics(s.x, s.h, s.sp, s.c, s.s, s.lane, s.tspeed, EDGE.limit)
    on = _on_lanes(s.x, s.y, EDGE.geo, EDGE.length, EDGE.vlen)
    old_f, old_r = _front_rear(s.lane[k], k, s.x, on)
    assert _mobil(k, side, old_f, old_r, s.x, on, s.params, s.idm_p, kin) == want


@FAST
@given(_cars, st.data())
def test_numpy_steering_is_highway_envs_steering_control(
    cars: list[dict], data: st.DataObject
) -> None:
    """``traffic.idm._steering`` (every car onto its target lane) is
    ``ControlledVehicle.steering_control``, clipped to ``MAX_STEERING_ANGLE``."""
    _, objs = _road(Road, cars)
    s = TrafficState(objs, EDGE)
    got = _steering(s, numpy_not_zero(s.sp))
    for k, car in enumerate(objs):
        want = car.steering_control(car.target_lane_index)
        want = float(np.clip(want, -car.MAX_STEERING_ANGLE, car.MAX_STEERING_ANGLE))
        assert got[k] == want


@FAST
@given(_car, st.booleans(), st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)))
def test_move_is_highway_envs_vehicle_step(car: dict, hit: bool, impact: tuple) -> None:
    """One car's ``IDMVehicle.step`` (``clip_actions``, the bicycle, a pending impact, the
    timer, the closest lane) as ``traffic.road.move`` (exactly) and ``traffic.jit._move``
    (to ``ULP``: numba's trigonometry) do it."""
    car = {**car, "v": car["v"] * 1.2 - 5.0}  # below MIN_SPEED and above MAX_SPEED too
    (want,) = _road(Road, [car])[1]
    if hit:
        want.impact = np.array(impact)
    twin = copy.deepcopy(want)
    s = TrafficState([twin], EDGE)
    want.step(DT)
    road_module.move(s, DT)
    moved = (s.x[0], s.y[0], s.h[0], s.sp[0], s.lane[0], s.timer[0], s.crashed[0])
    expect = (*want.position, want.heading, want.speed, want.lane_index[2], want.timer)
    assert moved == (*expect, want.crashed)
    s = TrafficState([twin], EDGE)
    _move(0, DT, s.x, s.y, s.h, s.sp, s.steer, s.acc, s.crashed, s.hit, s.impact,
          s.speed_range, s.half_len)  # fmt: skip
    assert (s.x[0], s.y[0], s.h[0], s.sp[0]) == pytest.approx(expect[:4], **ULP)
    assert s.crashed[0] == want.crashed
    assert (s.steer[0], s.acc[0]) == (want.action["steering"], want.action["acceleration"])


@FAST
@given(_cars)
def test_step_pairs_keep_every_pair_highway_env_collides(cars: list[dict]) -> None:
    """``traffic.jit.step``'s pairs (``_apart`` rules a pair out) are
    ``world.touching_pairs``' and hold every pair (i < j) whose bodies highway-env finds
    intersecting now or within the step (``Vehicle._is_colliding``: its pre-check, then
    ``utils.are_polygons_intersecting``)."""
    from openconvoy.envs.traffic.world import touching_pairs

    _, objs = _road(Road, cars)
    s = TrafficState(objs, EDGE)
    e = EDGE
    pairs = step(
        s.mover_rows[:0], DT, s.x, s.y, s.h, s.sp, s.c, s.s, s.steer, s.acc, s.crashed,
        s.hit, s.impact, s.speed_range, s.half, s.timer, s.lane, e.lane_y, e.length, s.reach,
    )  # fmt: skip
    got = {(int(i), int(j)) for i, j in pairs}
    assert got == set(touching_pairs(s.x, s.y, s.c, s.s, s.sp, s.reach, s.half, s.upper, DT))
    for i in range(len(objs)):
        for j in range(i + 1, len(objs)):
            a, b = objs[i], objs[j]
            # What ``Road.step``'s ``a.handle_collisions(b, dt)`` acts on: highway-env's
            # spherical pre-check, then ``utils.are_polygons_intersecting``.
            now, later, _ = a._is_colliding(b, DT)
            apart = _apart(i, j, s.x, s.y, s.c, s.s, s.sp, s.half, DT)
            if now or later:
                assert not apart and (i, j) in got


@FAST
@given(st.floats(-1e3, 1e3) | st.floats(-0.05, 0.05), st.floats(-50.0, 50.0))
def test_helpers_are_highway_envs_utils(v: float, w: float) -> None:
    """``traffic.jit._not_zero``, ``_wrap_to_pi``, ``_clip`` and ``traffic.idm._not_zero``
    are ``utils.not_zero``, ``utils.wrap_to_pi`` and ``np.clip``."""
    assert _not_zero(v) == utils.not_zero(v) == numpy_not_zero(np.array([v]))[0]
    assert _wrap_to_pi(w) == utils.wrap_to_pi(w)
    lo, hi = sorted((v, w))
    assert _clip(w * 2, lo, hi) == np.clip(w * 2, lo, hi)


_convoy_car = st.tuples(st.floats(0.0, 150.0), st.floats(-5.0, 13.0), st.floats(-0.5, 0.5))


@SOME
@given(_cars, _convoy_car, st.floats(0.0, 30.0), st.booleans())
def test_in_path_on_a_vector_road_is_the_worlds(
    cars: list[dict], pose: tuple, speed: float, compiled: bool
) -> None:
    """``TrafficWorld.in_path`` and ``place`` on a ``VectorRoad`` (``traffic.jit``'s
    ``nearest_in_path`` and ``place``) give what the same world gives on highway-env's
    ``Road`` (its numpy search, ``ConvoyVehicle.set_state``). Ranges to 1e-12 relative:
    the road's search takes cos/sin from numba's ``math``, the world's from numpy."""
    worlds = []
    for cls in (Road, VectorRoad):
        road, traffic = _road(cls, cars, compiled)
        world = TrafficWorld(HighwayFrame(100.0, 4.0), [4.8], [1.9], 25.0)
        world.reset(road, traffic)
        world.place([pose[0] - 100.0], [pose[1]], [pose[2]], [speed])
        worlds.append(world)
    placed = [[(*v.position, v.heading, v.speed, v.lane_index) for v in w.convoy] for w in worlds]
    assert placed[1] == placed[0]
    want, got = (w.in_path() for w in worlds)
    assert [p is None for p in got] == [p is None for p in want]
    for g, w in zip(got, want):
        if w is not None:
            assert (g.target_id, g.is_traffic, g.length_m) == (
                w.target_id,
                w.is_traffic,
                w.length_m,
            )
            assert g.range_m == pytest.approx(w.range_m, rel=1e-12, abs=1e-12)
            assert g.range_rate_mps == pytest.approx(w.range_rate_mps, rel=1e-12, abs=1e-12)
