"""Vectorized traffic on straight multi-lane roads: highway-env's IDM/MOBIL, all cars at once.

``VectorRoad`` is a highway-env ``Road`` that keeps its vehicles' state in numpy arrays for
the whole episode (``traffic.state.TrafficState``) and computes on them what every
``IDMVehicle`` on it would (``IDMVehicle.act``, ``Vehicle.step``), instead of vehicle by
vehicle: compiled (``traffic.jit``'s numba kernels, car by car in road order, the default)
or, without numba, with numpy calls over all cars (``traffic.idm.decide``, ``move``; one
log line says so). highway-env's vehicle objects stay the public face: reading
``road.vehicles`` (the renderer, highway-env's own code, ``TrafficWorld.convoy``) first
writes the arrays back into the objects, and the next tick reads the objects again (so
what a caller changed in them counts). Collisions are highway-env's ``handle_collisions``,
called on the objects of the pairs the arrays cannot rule out.

It applies to one road edge of parallel straight lanes along +x from x = 0
(``highway-cut-in``, ``highway-slow-traffic``) with plain ``IDMVehicle`` traffic (no
routes), ``ScriptedLaneChanger`` s and our ``ConvoyVehicle`` s, before any car reaches the
lane's end; anything else falls back to ``FastRoad`` (highway-env's per-vehicle code).
The parity tests hold both ways' trajectories to 1e-9 m of highway-env's own over whole
scenarios (they agree bit for bit on this machine: the same operations in the same order).
"""

from __future__ import annotations

import logging
from types import ModuleType
from typing import Any

import numpy as np

from openconvoy.core.errors import DependencyMissing
from openconvoy.envs.traffic.idm import decide
from openconvoy.envs.traffic.state import StraightEdge, TrafficState, vectorizable
from openconvoy.envs.traffic.world import FastRoad, StraightLane, touching_pairs

_jit: ModuleType | None
_told = False  # the one line about a missing numba was logged
try:
    from openconvoy.envs.traffic import jit as _jit
except DependencyMissing:  # numba comes with the traffic extra
    _jit = None
_NO_JIT = (
    "traffic road=vector: numba is missing, the traffic runs as numpy calls (~2x slower); "
    "pip install 'openconvoy[traffic]'"
)


def move(st: TrafficState, dt: float) -> None:
    """``IDMVehicle.step`` for every traffic car (timer, ``clip_actions``, the kinematic
    bicycle over ``dt`` s, a pending impact, the closest lane)."""
    m = st.movers
    if not st.mover_rows.size:  # only convoy vehicles: nothing moves, nothing to reduce
        return
    h, sp, steer, acc = st.h[m], st.sp[m], st.steer[m], st.acc[m]
    crashed = st.crashed[m]
    if crashed.any():  # erratic steering and braking until complete stop
        steer, acc = np.where(crashed, 0.0, steer), np.where(crashed, -1.0 * sp, acc)
    vmin, vmax = st.speed_range[:, m]
    if sp.max() > st.speed_bounds[1] or sp.min() < st.speed_bounds[0]:
        acc = np.where(
            sp > vmax,
            np.minimum(acc, 1.0 * (vmax - sp)),
            np.where(sp < vmin, np.maximum(acc, 1.0 * (vmin - sp)), acc),
        )
    st.steer[m], st.acc[m] = steer, acc
    beta = np.arctan(1 / 2 * np.tan(steer))
    x = st.x[m] + sp * np.cos(h + beta) * dt
    y = st.y[m] + sp * np.sin(h + beta) * dt
    hit = st.hit[m]
    if hit.any():
        imp = st.impact[m]
        x, y = np.where(hit, x + imp[:, 0], x), np.where(hit, y + imp[:, 1], y)
        st.crashed[m] = crashed | hit
        st.hit[m] = False
    h = h + sp * np.sin(beta) / st.half[m, 0] * dt
    st.x[m], st.y[m], st.h[m], st.sp[m] = x, y, h, sp + acc * dt
    st.lane[m] = st.edge.closest(x, y, h)
    st.timer[m] += dt
    st.trig_ok = False


class VectorRoad(FastRoad):
    """See the module doc. ``compiled``: run the tick as ``traffic.jit``'s kernels (numba;
    the default where it is installed), else as numpy calls (``traffic.idm``, ``move``)."""

    compiled: bool = _jit is not None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """highway-env's ``Road.__init__``, and the straight edge the arrays run on (None:
        a road this class cannot vectorize; property-tested with the whole tick,
        tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        global _told
        if _jit is None and not _told:
            logging.getLogger(__name__).warning("%s", _NO_JIT)
            _told = True
        self._veh: list = []
        self._st: TrafficState | None = None
        self._arrays_ok = False  # the arrays hold the current state
        self._objects_ok = True  # the objects do
        self._idm: np.ndarray | None = None
        super().__init__(*args, **kwargs)
        plain = not (self.neighbour_vehicles_connected_lanes or self.record_history)
        self._edge = StraightEdge.of(self.network.graph) if plain else None

    @property
    def vehicles(self) -> list:
        """highway-env's vehicle objects (``Road.vehicles``), brought up to date (and read
        again next tick; tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        if self._st is not None and not self._objects_ok:
            self._st.sync()
        self._objects_ok, self._arrays_ok = True, False
        return self._veh

    @vehicles.setter
    def vehicles(self, value: list) -> None:
        self._veh = value
        self._objects_ok, self._arrays_ok = True, False

    def vector_state(self, vehicles: list) -> TrafficState | None:
        """The arrays, when this road runs vectorized and ``vehicles`` is its list
        (``FastRoad.vector_state``; tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        return self._state() if vehicles is self._veh else None

    def _state(self) -> TrafficState | None:
        """The arrays of ``Road.vehicles``, read again from the objects when they may have
        changed; None when not vectorizable (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        if self._arrays_ok:
            return self._st
        veh = self._veh
        if self._edge is None or self.objects or not veh or not vectorizable(veh):
            return None
        st = self._st
        if (
            st is not None
            and len(st.objs) == len(veh)
            and all(map(lambda a, b: a is b, st.objs, veh))
        ):
            st.load()
        else:
            st = self._st = TrafficState(veh, self._edge)
            self._idm = None
        self._arrays_ok = True
        return st

    def closest_lane(
        self, hx: float, hy: float, heading: float
    ) -> tuple[tuple, StraightLane] | None:
        """``(lane_index, lane)`` that ``RoadNetwork.get_closest_lane_index`` picks for a
        vehicle at ``(hx, hy)`` (m) with ``heading`` (rad); None off a straight edge
        (tests/envs/traffic/test_traffic_twins.py::test_closest_lane_is_highway_envs)."""
        e = self._edge
        if e is None:
            return None
        k = int(
            e.closest(
                np.array([hx], dtype=float),
                np.array([hy], dtype=float),
                np.array([heading], dtype=float),
            )[0]
        )
        return (e.start, e.end, k), e.lanes[k]

    def place_vehicles(
        self, vehicles: list, hx: np.ndarray, hy: np.ndarray, heading: np.ndarray, speed: np.ndarray
    ) -> bool:
        """``ConvoyVehicle.set_state`` for ``vehicles`` at once (highway-env frame: m, rad,
        m/s), on the arrays; False (nothing done) when the road is not vectorized
        (tests/envs/traffic/test_traffic_road_twins.py::test_in_path_on_a_vector_road_is_the_worlds)."""
        st = self._state()
        if st is None:
            return False
        try:
            ks = st.rows_of(vehicles)
        except KeyError:  # not all on this road's list: the caller sets the objects
            self.vehicles  # noqa: B018  (brings the objects up to date, read back next tick)
            return False
        if self.compiled and _jit is not None:
            e = st.edge
            _jit.place(
                st.row_array(vehicles), hx, hy, heading, speed, st.x, st.y, st.h, st.sp,
                st.hit, st.lane, st.tgt, e.lane_y, e.length,
            )  # fmt: skip
        else:
            st.x[ks], st.y[ks], st.h[ks], st.sp[ks] = hx, hy, heading, speed
            st.hit[ks] = False
            st.lane[ks] = st.tgt[ks] = st.edge.closest(st.x[ks], st.y[ks], st.h[ks])
        st.trig_ok = False
        self._objects_ok = False
        return True

    def known_idm_accel(self, vehicle: Any) -> float | None:
        """``IDMVehicle.acceleration`` of ``vehicle`` on its lane, clipped (m/s²), as the
        last ``act`` computed it; None: not known (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        st = self._st
        if self._idm is None or st is None:
            return None
        k = st.index.get(id(vehicle))
        return None if k is None else float(self._idm[k])

    def nearest_in_path(
        self, vehicles: list, n: int, max_look_m: float
    ) -> tuple[list[int], list[float], list[float], np.ndarray] | None:
        """``FastRoad.nearest_in_path`` (``TrafficWorld.in_path``'s search) on the arrays,
        compiled; None: not done here (tests/envs/traffic/test_traffic_road_twins.py::test_in_path_on_a_vector_road_is_the_worlds)."""
        st = self._state() if vehicles is self._veh else None
        if st is None or not self.compiled or _jit is None:
            return None
        st.trig()
        target, rng, rate = np.empty(n, dtype=np.intp), np.zeros(n), np.zeros(n)
        _jit.nearest_in_path(
            n, st.x, st.y, st.sp, st.c, st.s, st.width, max_look_m, target, rng, rate
        )
        return target.tolist(), rng.tolist(), rate.tolist(), st.length

    def act(self) -> None:
        """highway-env's ``Road.act`` on the arrays (``traffic.jit.decide`` or
        ``traffic.idm.decide``), or its own code where they do not apply (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        self._idm = None
        st = self._state()
        if st is not None and self.compiled and _jit is not None:
            st.read_scripts()
            e = st.edge
            if _jit.decide(
                st.x, st.y, st.h, st.sp, st.c, st.s, st.lane, st.tgt, st.timer, st.crashed,
                st.tspeed, st.kind, st.params, st.idm_p, st.half_len, e.geo, e.limit,
                e.length, e.vlen, st.steer, st.acc, st.idm_out,
            ):  # fmt: skip
                self._idm, self._objects_ok, st.trig_ok = st.idm_out, False, True
                return
            st = None  # follow_road would switch lanes: highway-env's code
        end = None if self._edge is None else self._edge.length - self._edge.vlen / 2
        if st is None or (st.traffic & (st.x > end)).any():  # follow_road would switch lanes
            super().act()
            return
        self._idm = decide(st)
        self._objects_ok = False

    def step(self, dt: float) -> None:
        """highway-env's ``Road.step`` over ``dt`` s: the traffic moves on the arrays and
        highway-env's ``handle_collisions`` acts on the pairs they cannot rule out
        (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
        st = self._state()
        if st is None:
            super().step(dt)
            return
        self._objects_ok = False
        if self.compiled and _jit is not None:
            e = st.edge
            found = _jit.step(
                st.mover_rows, dt, st.x, st.y, st.h, st.sp, st.c, st.s, st.steer, st.acc,
                st.crashed, st.hit, st.impact, st.speed_range, st.half, st.timer, st.lane,
                e.lane_y, e.length, st.reach,
            )  # fmt: skip
            st.trig_ok = True
            pairs = [(int(i), int(j)) for i, j in found] if len(found) else []
        else:
            move(st, dt)
            st.trig()
            pairs = touching_pairs(st.x, st.y, st.c, st.s, st.sp, st.reach, st.half, st.upper, dt)
        if pairs:
            ks = sorted({k for pair in pairs for k in pair})
            st.sync(ks)
            for i, j in pairs:
                st.objs[i].handle_collisions(st.objs[j], dt)
            st.read_collisions(ks)
