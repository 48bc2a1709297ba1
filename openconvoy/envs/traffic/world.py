"""The traffic world: highway-env's road and IDM/MOBIL traffic around our convoy.

highway-env (``openconvoy[traffic]``) owns the road network, the traffic vehicles (its
``IDMVehicle``: IDM car following, MOBIL lane changes) and the collision check between
vehicle rectangles. The convoy keeps our plant, members, channel and policies; each of its
vehicles appears on highway-env's road as a ``ConvoyVehicle`` whose state we set every
tick, so traffic reacts to it (IDM brakes for it, MOBIL weighs it) and highway-env's
collision check sees it. Traffic has no V2V: the convoy sees it only through the forward
ranging sensor (``in_path``).

Frames: our ENU (x east, y north, heading counter-clockwise from east) and highway-env's
(x along the road, y across it towards higher lane indices, i.e. to the right of travel,
heading clockwise from x). ``enu_to_highway`` / ``highway_to_enu`` are the one mapping:
the convoy drives east, the ENU origin sits on the centre line of the convoy's lane.

One tick of the world (``advance``), at the end of the env's tick ``t``: set the convoy
vehicles to their plant states at ``t``; step traffic from ``t - dt`` to ``t`` with the
decisions it took at ``t - dt``; check collisions at ``t``; run scripted events; let
traffic decide (``Road.act``) on the state at ``t``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import numpy as np

from openconvoy.core.errors import DependencyMissing

try:  # the traffic extra, imported here only (the core never needs it)
    from highway_env.road.lane import LineType, SineLane, StraightLane
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.behavior import IDMVehicle
    from highway_env.vehicle.kinematics import Vehicle
    from highway_env.vehicle.objects import Landmark, Obstacle, RoadObject
except ModuleNotFoundError as exc:
    raise DependencyMissing(
        "highway-* scenarios need highway-env: pip install 'openconvoy[traffic]'",
        name="highway_env",
    ) from exc

__all__ = [
    "TRAFFIC_ID_BASE",
    "ConvoyVehicle",
    "FastRoad",
    "HighwayFrame",
    "IDMVehicle",
    "InPath",
    "LineType",
    "Obstacle",
    "Road",
    "RoadNetwork",
    "ScriptedLaneChanger",
    "SineLane",
    "StraightLane",
    "TrafficWorld",
    "collide",
    "enu_to_highway",
    "highway_to_enu",
]

F = TypeVar("F", float, np.ndarray)

TRAFFIC_ID_BASE = 1000
"""Traffic vehicle k is reported as id ``TRAFFIC_ID_BASE + k`` (convoy ids are 0..n-1)."""


@dataclass(frozen=True)
class HighwayFrame:
    """Where our ENU origin lies in highway-env's frame: ``(x0, y0)`` metres."""

    x0: float = 0.0
    y0: float = 0.0


def enu_to_highway(frame: HighwayFrame, x: F, y: F, heading: F) -> tuple[F, F, F]:
    """ENU position (m) and heading (rad, CCW from east) -> highway-env's x, y, heading
    (floats, or arrays of them).

    highway-env's y grows to the right of travel (its lane 0 is the leftmost lane), so the
    lateral axis and the heading change sign."""
    return frame.x0 + x, frame.y0 - y, -heading


def highway_to_enu(frame: HighwayFrame, hx: F, hy: F, heading: F) -> tuple[F, F, F]:
    """The inverse of ``enu_to_highway`` (floats or arrays, as it)."""
    return hx - frame.x0, frame.y0 - hy, -heading


class ConvoyVehicle(IDMVehicle):
    """A convoy vehicle on highway-env's road: state set from our plant, never stepped.

    An ``IDMVehicle`` so that traffic's MOBIL models it like any driver (with
    ``target_speed`` the convoy's cruise speed) and the leader can ask highway-env's IDM
    for its acceleration; ``act`` and ``step`` do nothing. Collisions with other convoy
    vehicles are left to ``ConvoyEnv``'s own rule; ``traffic_hit`` records a touch with
    traffic (highway-env's rectangle test)."""

    def __init__(
        self, road: Road, vehicle_id: int, length_m: float, width_m: float, target_speed: float
    ) -> None:
        self.LENGTH = float(length_m)
        self.WIDTH = float(width_m)
        super().__init__(
            road, np.zeros(2), 0.0, 0.0, target_speed=target_speed, enable_lane_change=False
        )
        self.vehicle_id = vehicle_id
        self.diagonal = math.hypot(self.LENGTH, self.WIDTH)
        self.traffic_hit = False
        self.color: tuple[int, int, int] | None = None

    def set_state(self, hx: float, hy: float, heading: float, speed: float) -> None:
        """Place the vehicle (highway-env frame) and update its lane."""
        self.position = np.array((hx, hy), dtype=np.float64)
        self.heading = heading
        self.speed = speed
        self.impact = None
        closest = getattr(self.road, "closest_lane", None)
        known = closest(hx, hy, heading) if closest is not None else None
        if known is None:
            self.on_state_update()
        else:  # a straight edge: the same choice as get_closest_lane_index, without its loop
            self.lane_index, self.lane = known
        self.target_lane_index = self.lane_index

    def act(self, action: dict | str | None = None) -> None:
        pass

    def step(self, dt: float) -> None:
        pass

    def handle_collisions(self, other: RoadObject, dt: float = 0) -> None:
        if isinstance(other, ConvoyVehicle):
            return
        super().handle_collisions(other, dt)
        # Only traffic and obstacles get here: ``crashed`` means a touch with one of them.
        self.traffic_hit = self.traffic_hit or self.crashed


class ScriptedLaneChanger(IDMVehicle):
    """A test-track target car: holds ``target_speed`` (highway-env's speed controller,
    ``KP_A * (target - speed)``, clipped to ``ACC_MAX``), keeps its lane with highway-env's
    steering law, and changes lane when told to, not by MOBIL: ``schedule`` holds
    ``(time_s, lane_id, target_speed_mps or None)`` applied by ``update(t)``. It does not
    react to the vehicles around it (as the target of a cut-in test does not)."""

    def __init__(
        self,
        road: Road,
        position: np.ndarray,
        heading: float,
        speed: float,
        schedule: Sequence[tuple[float, int, float | None]] = (),
        target_speed: float | None = None,
    ) -> None:
        super().__init__(
            road, position, heading, speed, target_speed=target_speed, enable_lane_change=False
        )
        self.schedule = sorted(schedule)

    def update(self, t: float) -> None:
        while self.schedule and self.schedule[0][0] <= t + 1e-9:
            _, lane_id, speed = self.schedule.pop(0)
            _from, _to, _ = self.lane_index
            self.target_lane_index = (_from, _to, lane_id)
            if speed is not None:
                self.target_speed = speed

    def act(self, action: dict | str | None = None) -> None:
        if self.crashed:
            return
        self.follow_road()
        steering = float(
            np.clip(
                self.steering_control(self.target_lane_index),
                -self.MAX_STEERING_ANGLE,
                self.MAX_STEERING_ANGLE,
            )
        )
        accel = float(np.clip(self.speed_control(self.target_speed), -self.ACC_MAX, self.ACC_MAX))
        Vehicle.act(self, {"steering": steering, "acceleration": accel})


class FastRoad(Road):
    """``Road`` with the same results, fewer repeated computations (the faster traffic
    path, ``TrafficConfig.fast``):

    - during ``act`` every vehicle's lane coordinates on a lane are computed once per lane
      (highway-env recomputes them for every query: O(n²) ``local_coordinates`` per act);
    - ``step`` calls ``handle_collisions`` only for pairs that pass highway-env's own
      spherical pre-check (done for all pairs at once with numpy, with a small margin so
      no pair that highway-env would test is skipped).

    The neighbour search reproduces ``Road.neighbour_vehicles`` decision for decision
    (the parity test runs both on the same seeds)."""

    _cache: dict | None = None

    # Seams for ``traffic.road.VectorRoad`` (state in arrays); here: use the objects.
    def vector_state(self, vehicles: list) -> Any:
        """The vehicles' state as arrays (``TrafficState``), None: read the objects."""
        return None

    def place_vehicles(
        self, vehicles: list, hx: np.ndarray, hy: np.ndarray, heading: np.ndarray, speed: np.ndarray
    ) -> bool:
        """Set convoy vehicles' states on the arrays; False: set the objects instead."""
        return False

    def known_idm_accel(self, vehicle: Any) -> float | None:
        """The IDM acceleration (m/s², clipped) ``act`` computed for ``vehicle``, if any."""
        return None

    def nearest_in_path(
        self, vehicles: list, n: int, max_look_m: float
    ) -> tuple[list[int], list[float], list[float], np.ndarray] | None:
        """``TrafficWorld.in_path``'s search for the first ``n`` of ``vehicles`` (the road's
        list), done on the arrays: per car the index of the one in its path (-1: none),
        range (m), range rate (m/s), and every car's length (m); None: not done here."""
        return None

    def act(self) -> None:
        self._cache = {}
        self._objs = [v for v in self.vehicles + self.objects if not isinstance(v, Landmark)]
        self._index = {id(v): k for k, v in enumerate(self._objs)}
        try:
            super().act()
        finally:
            self._cache = None

    def _coords(self, lane_index: tuple) -> tuple[np.ndarray, np.ndarray]:
        assert self._cache is not None, "only during act"
        got = self._cache.get(lane_index)
        if got is None:
            lane = self.network.get_lane(lane_index)
            s = np.empty(len(self._objs))
            on = np.empty(len(self._objs), dtype=bool)
            for k, v in enumerate(self._objs):
                sv, lat = lane.local_coordinates(v.position)
                s[k] = sv
                on[k] = lane.on_lane(v.position, sv, lat, margin=1)
            got = self._cache[lane_index] = (s, on)
        return got

    def neighbour_vehicles(self, vehicle, lane_index=None):
        if (
            self._cache is None
            or self.neighbour_vehicles_connected_lanes
            or id(vehicle) not in self._index
        ):
            return super().neighbour_vehicles(vehicle, lane_index)
        lane_index = lane_index or vehicle.lane_index
        if not lane_index:
            return None, None
        s_all, on = self._coords(lane_index)
        me = self._index[id(vehicle)]
        s = s_all[me]
        cand = on.copy()
        cand[me] = False
        front_mask = cand & (s_all >= s)
        rear_mask = cand & (s_all < s)
        v_front = v_rear = None
        if front_mask.any():
            idx = np.flatnonzero(front_mask)
            best = s_all[idx].min()
            v_front = self._objs[idx[s_all[idx] == best][-1]]  # Road keeps the last tie
        if rear_mask.any():
            idx = np.flatnonzero(rear_mask)
            best = s_all[idx].max()
            v_rear = self._objs[idx[s_all[idx] == best][0]]  # and the first tie behind
        return v_front, v_rear

    def step(self, dt: float) -> None:
        for vehicle in self.vehicles:
            vehicle.step(dt)
        collide(self, dt)


_shape_key: tuple = ()
_shape_val: tuple = ()
_shape_items: list = []  # held so that the ids in the key stay theirs


def _shapes(items: list, n_v: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half the diagonals' sums (m, n x n), half (length, width) (m) of ``items`` and the
    pairs to test (i < j, i one of the first ``n_v``), read once per set of objects."""
    global _shape_key, _shape_val, _shape_items
    key = (n_v, *map(id, items))
    if key != _shape_key:
        _shape_key, _shape_items = key, items
        diag = np.array([o.diagonal for o in items])
        upper = np.triu(np.ones((len(items), len(items)), dtype=bool), 1)
        upper[n_v:, :] = False
        _shape_val = (
            0.5 * (diag[:, None] + diag[None, :]),
            0.5 * np.array([(o.LENGTH, o.WIDTH) for o in items], dtype=float),
            upper,
        )
    return _shape_val


def touching_pairs(
    x: np.ndarray,
    y: np.ndarray,
    c: np.ndarray,
    s: np.ndarray,
    speed: np.ndarray,
    reach: np.ndarray,
    half: np.ndarray,
    pairs: np.ndarray,
    dt: float,
) -> list[tuple[int, int]]:
    """The pairs among ``pairs`` (n x n mask) for which highway-env's ``handle_collisions``
    may find a touch, in its (row-major) order: all but those failing its spherical
    pre-check (``reach``: half the diagonals' sum, m) and those its separating-axis test
    (``are_polygons_intersecting``, on the rectangles' edge normals) finds apart both now
    and after ``dt`` s, with a 1e-9 m margin. Positions (m), cos and sin of the headings,
    speeds (m/s), ``half``: half (length, width) (m)."""
    dx, dy = x[:, None] - x, y[:, None] - y
    # highway-env skips a pair when dist > (d_i + d_j)/2 + speed_i * dt; keep a margin.
    r = reach + (np.abs(speed) * dt + 1e-6)[:, None]
    ii, jj = ((dx * dx + dy * dy <= r * r) & pairs).nonzero()
    if not len(ii):
        return []
    g = np.array((x, y, c, s, half[:, 0], half[:, 1], speed * c * dt, speed * s * dt))
    xi, yi, ci, si, li, wi, ui, vi = g[:, ii]
    xj, yj, cj, sj, lj, wj, uj, vj = g[:, jj]
    # The four axes: each rectangle's heading and its normal. On axis u a rectangle spans
    # its centre's projection +- (l |u.d| + w |u.n|); |cos|, |sin| of the heading difference.
    ac, as_ = np.abs(ci * cj + si * sj), np.abs(si * cj - ci * sj)
    ux, uy = np.array((ci, -si, cj, -sj)), np.array((si, ci, sj, cj))
    ext = np.array(
        (
            li + lj * ac + wj * as_,
            wi + lj * as_ + wj * ac,
            lj + li * ac + wi * as_,
            wj + li * as_ + wi * ac,
        )
    )
    proj = (xj - xi) * ux + (yj - yi) * uy  # j's centre relative to i's
    vp = (ui - uj) * ux + (vi - vj) * uy  # i's displacement relative to j's, as highway-env
    now = (np.abs(proj) - ext > 1e-9).any(axis=0)
    # i's interval stretched by vp (highway-env's will_intersect), then the gap to j's.
    later = np.maximum(proj - ext - np.maximum(vp, 0.0), np.minimum(vp, 0.0) - proj - ext)
    maybe = (~(now & (later > 1e-9).any(axis=0))).nonzero()[0]
    return list(zip(ii[maybe].tolist(), jj[maybe].tolist()))


def collide(road: Road, dt: float) -> None:
    """``Road.step``'s collision pass with the same outcome: highway-env's
    ``handle_collisions`` runs, in its order, for every vehicle–vehicle and vehicle–object
    pair except those that numpy shows cannot touch (``touching_pairs``)."""
    items = road.vehicles + road.objects
    n_v = len(road.vehicles)
    if len(items) < 2:
        return
    pos = np.array([o.position for o in items], dtype=float)
    reach, half, pairs = _shapes(items, n_v)
    speed = np.array([float(o.speed) if k < n_v else 0.0 for k, o in enumerate(items)])
    heading = np.array([float(o.heading) for o in items])
    c, s = np.cos(heading), np.sin(heading)
    for i, j in touching_pairs(pos[:, 0], pos[:, 1], c, s, speed, reach, half, pairs, dt):
        items[i].handle_collisions(items[j], dt)


class InPath(NamedTuple):  # a NamedTuple: built three times a tick, 4x cheaper than a dataclass
    """The nearest vehicle in a convoy vehicle's path, ahead of it (ground truth):
    centre-to-centre range (m), range rate (m/s, negative = closing), its length (m), its
    id (convoy id, or ``TRAFFIC_ID_BASE + k`` for traffic) and whether it is traffic."""

    range_m: float
    range_rate_mps: float
    length_m: float
    target_id: int
    is_traffic: bool


_DIAGONALS: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _diagonal(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays of an n x n diagonal (cached)."""
    got = _DIAGONALS.get(n)
    if got is None:
        got = _DIAGONALS[n] = (np.arange(n), np.arange(n))
    return got


class TrafficWorld:
    """highway-env's ``Road`` with our convoy on it (see the module doc).

    ``reset`` takes a built road (traffic already on it) and the convoy's proxies are put
    first in ``road.vehicles`` (so every convoy–traffic pair is tested by the convoy
    vehicle's ``handle_collisions``). On a ``VectorRoad`` the state lives in its arrays;
    ``convoy`` and ``traffic`` give the highway-env objects brought up to date."""

    def __init__(
        self,
        frame: HighwayFrame,
        lengths: Sequence[float],
        widths: Sequence[float],
        cruise_speed_mps: float,
        max_look_m: float = 250.0,
    ) -> None:
        self.frame = frame
        self.lengths = list(lengths)
        self.widths = list(widths)
        self.cruise_speed_mps = cruise_speed_mps
        self.max_look_m = max_look_m
        self.road: Road | None = None
        self._convoy: list[ConvoyVehicle] = []
        self._traffic: list[IDMVehicle] = []
        self._all: list[Vehicle] = []
        self._scripted: list[ScriptedLaneChanger] = []
        self.t = 0.0

    @property
    def convoy(self) -> list[ConvoyVehicle]:
        """The convoy's highway-env vehicles (up to date; changes to them count)."""
        self._objects()
        return self._convoy

    @property
    def traffic(self) -> list[IDMVehicle]:
        """The traffic's highway-env vehicles (up to date; changes to them count)."""
        self._objects()
        return self._traffic

    def _road(self) -> Road:
        assert self.road is not None, "reset() first"
        return self.road

    def _objects(self) -> None:
        if self.road is not None:
            self.road.vehicles  # noqa: B018  (reading them brings a VectorRoad's objects up to date)

    def reset(self, road: Road, traffic: Sequence[IDMVehicle]) -> None:
        self.road = road
        self._convoy = [
            ConvoyVehicle(road, i, length, width, self.cruise_speed_mps)
            for i, (length, width) in enumerate(zip(self.lengths, self.widths))
        ]
        self._traffic = list(traffic)
        self._scripted = [v for v in self._traffic if isinstance(v, ScriptedLaneChanger)]
        self._all = [*self._convoy, *self._traffic]
        road.vehicles = self._all
        self.t = 0.0

    def place(
        self,
        x: Sequence[float] | np.ndarray,
        y: Sequence[float] | np.ndarray,
        heading: Sequence[float] | np.ndarray,
        speed: Sequence[float] | np.ndarray,
    ) -> None:
        """Set every convoy vehicle from ENU states (m, rad, m/s)."""
        f = self.frame
        hx, hy, hh = enu_to_highway(
            f,
            np.asarray(x, dtype=float),
            np.asarray(y, dtype=float),
            np.asarray(heading, dtype=float),
        )
        sp = np.asarray(speed, dtype=float)
        road = self.road
        if isinstance(road, FastRoad) and road.place_vehicles(self._convoy, hx, hy, hh, sp):
            return
        for k, v in enumerate(self._convoy):
            v.set_state(float(hx[k]), float(hy[k]), float(hh[k]), float(sp[k]))

    def act(self, t: float) -> None:
        """Scripted events due at ``t``, then traffic decides on the state at ``t``."""
        for v in self._scripted:
            v.update(t)
        self._road().act()

    def step(self, dt: float) -> None:
        """Traffic moves ``dt`` seconds (convoy vehicles were placed already) and highway-env
        checks collisions."""
        self._road().step(dt)
        self.t += dt

    def traffic_hits(self) -> list[bool]:
        """Per convoy vehicle: has it touched a traffic vehicle (ever, this episode)?"""
        return [v.traffic_hit for v in self._convoy]

    def _arrays(self) -> tuple[np.ndarray, ...]:
        """Convoy then traffic: x, y, heading, speed, width, length, cos and sin of the
        heading (highway-env frame)."""
        road = self.road
        st = road.vector_state(self._all) if isinstance(road, FastRoad) else None
        if st is not None:
            st.trig()
            got = (st.x, st.y, st.h, st.sp, st.width, st.length, st.c, st.s)
            m = len(self._all)
            return got if m == st.n else tuple(a[:m] for a in got)
        rows = [
            (o.position[0], o.position[1], o.heading, o.speed, o.WIDTH, o.LENGTH) for o in self._all
        ]
        x, y, h, sp, w, length = np.array(rows, dtype=float).reshape(len(rows), 6).T
        return x, y, h, sp, w, length, np.cos(h), np.sin(h)

    def in_path(self) -> list[InPath | None]:
        """For each convoy vehicle, the nearest vehicle ahead whose body overlaps its path
        (the corridor of its own width straight ahead), within ``max_look_m``."""
        n = len(self._convoy)
        road = self.road
        found = (
            road.nearest_in_path(self._all, n, self.max_look_m)
            if isinstance(road, FastRoad)
            else None
        )
        if found is None:
            found = self._nearest_in_path()
        nearest, rngs, rates, lengths = found
        out: list[InPath | None] = []
        for i in range(n):
            j = nearest[i]
            if j < 0:
                out.append(None)
                continue
            traffic = j >= n
            tid = TRAFFIC_ID_BASE + (j - n) if traffic else j
            out.append(InPath(rngs[i], rates[i], float(lengths[j]), tid, traffic))
        return out

    def _nearest_in_path(self) -> tuple[list[int], list[float], list[float], np.ndarray]:
        """``FastRoad.nearest_in_path`` with numpy, on any road."""
        x, y, _, spd, width, lengths, c, s = self._arrays()
        n = len(self._convoy)
        half_w = 0.5 * width
        # Every convoy vehicle at once: rows = convoy vehicle i, columns = every object.
        dx, dy = x - x[:n, None], y - y[:n, None]
        cn, sn = c[:n, None], s[:n, None]
        lon = dx * cn + dy * sn
        ok = (
            (lon > 0.0)
            & (np.abs(-dx * sn + dy * cn) < half_w + half_w[:n, None])
            & (lon < self.max_look_m)
        )
        ok[_diagonal(n)] = False
        nearest = np.where(ok, lon, np.inf).argmin(axis=1).tolist()
        seen = ok.any(axis=1).tolist()
        vx, vy = (spd * c).tolist(), (spd * s).tolist()
        rngs, rates = [0.0] * n, [0.0] * n
        for i in range(n):
            if not seen[i]:
                nearest[i] = -1
                continue
            j = nearest[i]
            dxi, dyi = float(dx[i, j]), float(dy[i, j])
            rng = rngs[i] = math.hypot(dxi, dyi)
            rates[i] = (dxi * (vx[j] - vx[i]) + dyi * (vy[j] - vy[i])) / rng if rng > 0 else 0.0
        return nearest, rngs, rates, lengths

    def traffic_states_enu(self) -> np.ndarray:
        """Traffic as rows ``(x, y, heading, speed, length, width)`` in ENU."""
        x, y, h, sp, w, length, _, _ = (a[len(self._convoy) :] for a in self._arrays())
        ex, ey, eh = highway_to_enu(self.frame, x, y, h)
        return np.stack((ex, ey, eh, sp, length, w), axis=1).reshape(-1, 6)

    def leader_idm_accel(self) -> float:
        """highway-env's IDM acceleration (m/s²) for the leader behind whatever is ahead of
        it on its lane (traffic or obstacle), towards the cruise speed."""
        lead = self._convoy[0]
        if isinstance(self.road, FastRoad):
            known = self.road.known_idm_accel(lead)  # VectorRoad computed it in act
            if known is not None:
                return known
        self._objects()
        front, _ = self._road().neighbour_vehicles(lead, lead.lane_index)
        a = lead.acceleration(ego_vehicle=lead, front_vehicle=front)
        return float(np.clip(a, -lead.ACC_MAX, lead.ACC_MAX))
