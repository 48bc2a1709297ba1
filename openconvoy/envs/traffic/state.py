"""Every vehicle on a straight multi-lane road as arrays: ``VectorRoad``'s memory.

``StraightEdge`` is the road (one edge of parallel straight lanes along +x from x = 0, all
of one length, each with a speed limit); ``TrafficState`` holds the vehicles' state and
fixed parameters as numpy arrays, index k = ``road.vehicles[k]``, in highway-env's frame
and units (m, rad, m/s, s). ``load`` reads them from highway-env's vehicle objects,
``sync`` writes them back (only when someone asks for the objects).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from openconvoy.envs.traffic.world import (
    ConvoyVehicle,
    IDMVehicle,
    ScriptedLaneChanger,
    StraightLane,
)

_VECTOR_TYPES = (IDMVehicle, ScriptedLaneChanger, ConvoyVehicle)

# Rows of TrafficState.params (highway-env's class attributes of each vehicle).
PARAM_NAMES = (
    "COMFORT_ACC_MAX",
    "COMFORT_ACC_MIN",
    "DISTANCE_WANTED",
    "TIME_WANTED",
    "DELTA",
    "ACC_MAX",
    "POLITENESS",
    "LANE_CHANGE_MIN_ACC_GAIN",
    "LANE_CHANGE_MAX_BRAKING_IMPOSED",
    "LANE_CHANGE_DELAY",
    "LENGTH",
    "KP_LATERAL",
    "KP_HEADING",
    "MAX_STEERING_ANGLE",
    "KP_A",
)
(
    CAM,
    CAMIN,
    DW,
    TW,
    DELTA,
    AMAX,
    POLITE,
    GAIN,
    BRAKE,
    DELAY,
    LENGTH,
    KP_LAT,
    KP_HEAD,
    MAX_STEER,
    KP_A,
) = range(len(PARAM_NAMES))


# highway-env's IDM as plain functions on floats (and elementwise on arrays): the
# compiled kernels (``traffic.jit``) and the numpy form (``traffic.idm``) both call them.


def closing_speed(
    vx: float, vy: float, front_vx: float, front_vy: float, c: float, s: float
) -> float:
    """How fast a car closes on the one ahead (m/s): their velocity difference (m/s)
    along the car's heading (cosine ``c``, sine ``s``), ``IDMVehicle.desired_gap``'s
    projected ``dv``."""
    return (vx - front_vx) * c + (vy - front_vy) * s


def desired_gap(d0: float, tau: float, root: float, speed: float, closing: float) -> float:
    """IDM's desired gap (m): ``d0 + v·T + v·dv / root``, ``root`` = 2·sqrt(a·b)."""
    return d0 + speed * tau + speed * closing / root


def idm_free(amax: float, ratio: float, delta: float) -> float:
    """IDM's free-road acceleration (m/s²) at ``ratio`` = speed / target speed."""
    return amax * (1 - ratio**delta)


def idm_interaction(amax: float, d_star: float, gap: float) -> float:
    """IDM's braking term (m/s²) for desired gap ``d_star`` and gap ``gap`` (m, not zero)."""
    return amax * (d_star / gap) ** 2


@dataclass(frozen=True)
class StraightEdge:
    """The one road edge ``(start, end)``; per-lane arrays indexed by lane id."""

    start: str
    end: str
    lanes: tuple[StraightLane, ...]
    lane_y: np.ndarray  # lateral position of each lane's centre line (m)
    on_half_w: np.ndarray  # half width + highway-env's 1 m ``on_lane`` margin (m)
    reach_w: np.ndarray  # ``is_reachable_from``'s lateral reach: two lane widths (m)
    limit: np.ndarray  # speed limit (m/s)
    length: float  # lane length (m)
    vlen: float  # highway-env's VEHICLE_LENGTH (m), its margin at lane ends
    geo: np.ndarray  # (3, lanes): lane_y, reach_w, on_half_w (``traffic.jit.decide``'s)

    @classmethod
    def of(cls, graph: dict) -> StraightEdge | None:
        """The edge of a one-edge network of such lanes, else None."""
        if len(graph) != 1:
            return None
        ((start, tos),) = graph.items()
        if len(tos) != 1:
            return None
        ((end, lanes),) = tos.items()
        for ln in lanes:
            if (
                type(ln) is not StraightLane
                or ln.start[0] != 0.0
                or ln.direction[0] != 1.0
                or ln.direction[1] != 0.0
                or ln.forbidden
                or ln.speed_limit is None
                or ln.length != lanes[0].length
            ):
                return None
        lane_y = np.array([ln.start[1] for ln in lanes], dtype=float)
        on_half_w = np.array([ln.width / 2 + 1.0 for ln in lanes], dtype=float)
        reach_w = np.array([2 * ln.width for ln in lanes], dtype=float)
        return cls(
            start,
            end,
            tuple(lanes),
            lane_y,
            on_half_w,
            reach_w,
            np.array([ln.speed_limit for ln in lanes], dtype=float),
            float(lanes[0].length),
            float(lanes[0].VEHICLE_LENGTH),
            np.array((lane_y, reach_w, on_half_w)).reshape(3, len(lanes)),
        )

    def closest(self, x: np.ndarray, y: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Lane ids ``RoadNetwork.get_closest_lane_index`` picks for vehicles at ``(x, y)``
        (m) with ``heading`` (rad): its ``distance_with_heading``, term by term."""
        angle = np.abs((heading + np.pi) % (2 * np.pi) - np.pi)  # every lane heads along +x
        r = np.abs(y[:, None] - self.lane_y)
        if 0 <= x.min() and x.max() <= self.length:  # then both end terms are 0
            dist = r + angle[:, None]
        else:
            along = np.maximum(x - self.length, 0) + np.maximum(0 - x, 0)
            dist = r + along[:, None] + angle[:, None]
        return dist.argmin(axis=1)


def vectorizable(vehicles: list) -> bool:
    """Only convoy vehicles and route-less IDM / scripted traffic?"""
    for v in vehicles:
        t = type(v)
        if t not in _VECTOR_TYPES or (t is not ConvoyVehicle and v.route):
            return False
    return True


class TrafficState:
    """The vehicles of a ``VectorRoad`` as arrays (see the module doc). ``params`` is
    (len(PARAM_NAMES), n); ``movers`` the traffic (what ``step`` moves: not convoy),
    a slice when it is one block."""

    def __init__(self, vehicles: list, edge: StraightEdge) -> None:
        self.objs = list(vehicles)  # held: ``index`` keys are their ids
        self.edge = edge
        n = self.n = len(vehicles)
        self.index = {id(v): k for k, v in enumerate(vehicles)}
        self._rows: dict[int, tuple[list, slice | np.ndarray, np.ndarray]] = {}
        self.arange = np.arange(n)
        self.traffic = np.array([type(v) is not ConvoyVehicle for v in vehicles], dtype=bool)
        self.hold = np.array([type(v) is ScriptedLaneChanger for v in vehicles], dtype=bool)
        self.scripted = np.flatnonzero(self.hold).tolist()
        self.upper = np.triu(np.ones((n, n), dtype=bool), 1)
        first = int(np.argmax(self.traffic)) if self.traffic.any() else n
        block = not self.traffic[:first].any() and self.traffic[first:].all()
        self.movers: slice | np.ndarray = slice(first, n) if block else np.flatnonzero(self.traffic)
        self.mover_rows = np.flatnonzero(self.traffic)
        self.idm_out = np.zeros(n)
        self.load()

    def _read_parameters(self) -> None:
        """The vehicles' parameters (highway-env's class attributes, which a caller may set
        on an object: ``randomize_behavior``, ``enable_lane_change``, ...)."""
        vehicles, n = self.objs, self.n
        self.params = np.array(
            [[float(getattr(v, k)) for v in vehicles] for k in PARAM_NAMES], dtype=float
        ).reshape(len(PARAM_NAMES), n)
        # IDM's parameters as ``traffic.idm.idm`` reads them: COMFORT_ACC_MAX, DELTA,
        # DISTANCE_WANTED, TIME_WANTED and 2 sqrt(-COMFORT_ACC_MAX * COMFORT_ACC_MIN).
        p = self.params
        self.idm_p = np.array(
            (p[CAM], p[DELTA], p[DW], p[TW], 2 * np.sqrt(-p[CAM] * p[CAMIN]))
        ).reshape(5, n)
        self.neg_kp_lat, self.neg_max_steer = -p[KP_LAT], -p[MAX_STEER]
        self.lc = np.array([bool(v.enable_lane_change) for v in vehicles], dtype=bool)
        self.width = np.array([v.WIDTH for v in vehicles], dtype=float)
        self.length = np.array([v.LENGTH for v in vehicles], dtype=float)
        self.diagonal = np.array([v.diagonal for v in vehicles], dtype=float)
        self.speed_range = np.array(
            [[v.MIN_SPEED for v in vehicles], [v.MAX_SPEED for v in vehicles]], dtype=float
        ).reshape(2, n)
        # Speeds inside (min of MIN_SPEED, max of MAX_SPEED) need no clipping (m/s).
        self.speed_bounds = (
            (float(self.speed_range[0].max()), float(self.speed_range[1].min()))
            if n
            else (0.0, 0.0)
        )
        # Collision pre-check constants: half (length, width), half the diagonals' sum.
        half = np.array([(v.LENGTH, v.WIDTH) for v in vehicles], dtype=float).reshape(n, 2)
        self.half = 0.5 * half
        self.half_len = self.half[:, 0].copy()
        self.reach = 0.5 * (self.diagonal[:, None] + self.diagonal[None, :])
        # What ``traffic.jit.decide`` runs for each car: 0 nothing (convoy), 1 IDM, 2 IDM
        # and MOBIL, 3 a scripted car's speed control.
        self.kind = np.where(self.hold, 3, np.where(self.lc, 2, 1) * self.traffic).astype(np.intp)

    def load(self) -> None:
        """Read every vehicle's state and parameters from its highway-env object."""
        self._read_parameters()
        rows = [
            (
                v.position[0],
                v.position[1],
                v.heading,
                v.speed,
                v.lane_index[2],
                v.target_lane_index[2],
                v.timer,
                v.crashed,
                v.target_speed,
                v.action.get("steering", 0.0),
                v.action.get("acceleration", 0.0),
            )
            for v in self.objs
        ]
        cols = np.array(rows, dtype=float).reshape(self.n, 11).T.copy()
        self.x, self.y, self.h, self.sp = cols[0], cols[1], cols[2], cols[3]
        self.lane, self.tgt = cols[4].astype(np.intp), cols[5].astype(np.intp)
        self.timer, self.crashed, self.tspeed = cols[6], cols[7] != 0.0, cols[8]
        self.steer, self.acc = cols[9], cols[10]
        self.c, self.s = np.cos(self.h), np.sin(self.h)
        self.trig_ok = True
        self.impact = np.zeros((self.n, 2))
        self.hit = np.zeros(self.n, dtype=bool)  # an impact is pending (``impact is not None``)
        for k, v in enumerate(self.objs):
            if v.impact is not None:
                self.impact[k], self.hit[k] = v.impact, True

    def rows_of(self, vehicles: list) -> slice | np.ndarray:
        """The rows of ``vehicles`` (a slice when they are a block), cached per list."""
        return self._rows_entry(vehicles)[1]

    def row_array(self, vehicles: list) -> np.ndarray:
        """The rows of ``vehicles`` as an index array, cached per list."""
        return self._rows_entry(vehicles)[2]

    def _rows_entry(self, vehicles: list) -> tuple[list, slice | np.ndarray, np.ndarray]:
        got = self._rows.get(id(vehicles))
        if got is None or got[0] is not vehicles or len(got[2]) != len(vehicles):
            ks = np.array([self.index[id(v)] for v in vehicles], dtype=np.intp)
            block = len(ks) > 0 and bool(np.all(ks == np.arange(ks[0], ks[0] + len(ks))))
            rows = slice(int(ks[0]), int(ks[0]) + len(ks)) if block else ks
            got = self._rows[id(vehicles)] = (vehicles, rows, ks)
        return got

    def trig(self) -> None:
        """``c``, ``s``: cos and sin of every heading (computed once per change of ``h``)."""
        if not self.trig_ok:
            self.c, self.s = np.cos(self.h), np.sin(self.h)
            self.trig_ok = True

    def sync(self, ks: list[int] | None = None) -> None:
        """Write the state of vehicles ``ks`` (default: all) to their objects."""
        e = self.edge
        for k in range(self.n) if ks is None else ks:
            v = self.objs[k]
            v.position = np.array((self.x[k], self.y[k]), dtype=float)
            v.heading, v.speed = float(self.h[k]), float(self.sp[k])
            lane, tgt = int(self.lane[k]), int(self.tgt[k])
            if v.lane_index[2] != lane:
                v.lane_index, v.lane = (e.start, e.end, lane), e.lanes[lane]
            if v.target_lane_index[2] != tgt:
                v.target_lane_index = (e.start, e.end, tgt)
            v.timer = float(self.timer[k])
            v.crashed = bool(self.crashed[k])
            v.impact = self.impact[k].copy() if self.hit[k] else None
            v.action = {"steering": float(self.steer[k]), "acceleration": float(self.acc[k])}

    def read_collisions(self, ks: list[int]) -> None:
        """Read back what ``handle_collisions`` changed on objects ``ks``."""
        for k in ks:
            v = self.objs[k]
            self.crashed[k] = bool(v.crashed)
            self.hit[k] = v.impact is not None
            if self.hit[k]:
                self.impact[k] = v.impact

    def read_scripts(self) -> None:
        """Scripted cars' targets (lane, speed) as their schedules last set them."""
        for k in self.scripted:
            v: Any = self.objs[k]
            self.tgt[k] = v.target_lane_index[2]
            self.tspeed[k] = v.target_speed
