"""Highway scenarios: the convoy in highway-env traffic (needs ``openconvoy[traffic]``).

Specs (``make_highway_scenario``), each with any number of followers, full-size cars with a
forward radar by default, traffic randomized by the episode's seed:

- ``highway-cut-in``: three lanes, the convoy in the middle one at 25 m/s; a car without
  V2V starts beside gap ``cut_in_gap`` (1 = between the leader and follower 1) in the
  lane to the left (shifted by ``cut_in_offset_m``) at the convoy's speed, and at
  ``cut_in_at_s`` changes into the convoy's lane, slowing to ``cut_in_speed_mps`` (22 m/s;
  negative: the convoy's speed), like the target car of a cut-in test (holding its speed,
  not reacting to others); back out at ``cut_out_at_s`` (never if negative). Other traffic (IDM/MOBIL) in the
  outer lanes only.
- ``highway-slow-traffic``: slower IDM traffic (``slow_speed_mps``) ``slow_ahead_m`` ahead
  of the leader, in every lane; the leader's IDM follows it.
- ``highway-merge``: the convoy in the right lane of the highway, an on-ramp joining it
  ``merge_at_m`` ahead of the leader (highway-env's merge road: straight ramp, sine
  converge, parallel merge lane ending at an obstacle); ``merge_cars`` ramp cars timed to
  reach the merge ``merge_offset_m`` ahead of the leader (smaller or negative: beside the
  convoy), 25 m apart, merging by MOBIL. MOBIL refuses a gap that would make the convoy
  vehicle behind brake harder than 2 m/s² by its IDM model of it (about 37 m ahead of a
  car at 25 m/s), so ramp cars merge ahead of or behind the convoy, or wait at the ramp's
  end; a car forced into a convoy gap is ``highway-cut-in``.
- ``highway-lane-drop``: three lanes, the right one ends ``drop_at_m`` ahead of the
  leader (an obstacle at its end); the convoy in the middle lane; ``drop_cars`` cars in the
  ending lane (ahead of the leader, beside the convoy) must merge into the convoy's lane.

The leader is driven by highway-env's IDM (its ``IDMVehicle.acceleration`` towards
``speed_mps`` behind whatever is ahead in its lane) along its lane's centre line.
Parameters: ``spec:key=value,key=value`` with ``HighwayConfig``'s field names, strictly.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from openconvoy.comms.geodesy import Origin
from openconvoy.core.errors import ConfigError
from openconvoy.core.spacing import SpacingConfig, SpacingPolicy
from openconvoy.envs.path import Path, straight_road
from openconvoy.envs.scenarios import DEFAULT_ORIGIN, InitialState
from openconvoy.envs.traffic.road import VectorRoad
from openconvoy.envs.traffic.world import (
    FastRoad,
    HighwayFrame,
    IDMVehicle,
    LineType,
    Obstacle,
    Road,
    RoadNetwork,
    ScriptedLaneChanger,
    SineLane,
    StraightLane,
    TrafficWorld,
)
from openconvoy.envs.vehicles import VEHICLE_PRESETS, RangingSensor, VehiclePreset

HIGHWAY_SCENARIOS: tuple[str, ...] = (
    "highway-cut-in",
    "highway-slow-traffic",
    "highway-merge",
    "highway-lane-drop",
)

LANE_WIDTH_M = StraightLane.DEFAULT_WIDTH
ROADS: tuple[str, ...] = ("vector", "fast", "highway-env")
"""Traffic paths (``HighwayConfig.road``): ``vector`` (``traffic.road.VectorRoad``: the
cars' state in arrays, the tick compiled by numba, on straight roads; ``fast`` elsewhere),
``fast`` (``FastRoad``:
highway-env's vehicles, its neighbour search and collision pre-check done once per step),
``highway-env`` (its ``Road`` as is)."""
RADAR = RangingSensor(max_range_m=150.0, range_noise_m=0.1, range_rate_noise_mps=0.1)
"""The full-size cars' forward radar (a long-range automotive radar: 150 m)."""
CAR = VEHICLE_PRESETS["full-size"].with_ranging(RADAR)
CACC = SpacingConfig("constant-time-headway", standstill_m=2.0, headway_s=0.6)


MAX_TRAFFIC = 500
"""Most traffic cars (``traffic``, ``merge_cars``) a highway scenario takes: each is
stepped every tick (100,000 ran for minutes, issue 22 D68)."""
MAX_LANES = 10


@dataclass(frozen=True)
class HighwayConfig:
    """A highway scenario's numbers (SI). Traffic speeds are IDM target speeds."""

    lanes: int = 3
    speed_mps: float = 25.0
    duration_s: float = 45.0
    traffic: int = 6
    traffic_speed_min_mps: float = 20.0
    traffic_speed_max_mps: float = 30.0
    road: str = "vector"
    # highway-cut-in
    cut_in_at_s: float = 3.0
    cut_out_at_s: float = 8.0
    cut_in_gap: int = 1
    cut_in_speed_mps: float = 22.0
    cut_in_offset_m: float = 0.0
    # highway-slow-traffic
    slow_speed_mps: float = 15.0
    slow_ahead_m: float = 120.0
    # highway-merge
    merge_cars: int = 1
    merge_at_m: float = 250.0
    merge_offset_m: float = 70.0
    # highway-lane-drop
    drop_at_m: float = 300.0
    drop_cars: int = 2

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"highway {f.name} must be a finite number, got {value}")
        if not 2 <= self.lanes <= MAX_LANES:
            raise ConfigError(
                f"highway scenarios need 2..{MAX_LANES} lanes, got lanes={self.lanes}"
            )
        for name in ("cut_in_at_s", "cut_out_at_s"):
            if getattr(self, name) < 0:
                raise ConfigError(f"highway {name} must be >= 0 s, got {getattr(self, name)}")
        for name in ("traffic", "merge_cars"):
            if getattr(self, name) > MAX_TRAFFIC:
                raise ConfigError(
                    f"highway {name} must be at most {MAX_TRAFFIC}, got {getattr(self, name)}"
                )
        for name in ("speed_mps", "duration_s", "traffic_speed_max_mps"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"highway {name} must be positive, got {getattr(self, name)}")
        if self.traffic < 0 or self.merge_cars < 0 or not 0 <= self.drop_cars <= 2:
            raise ConfigError("highway traffic and merge_cars must be >= 0, drop_cars 0..2")
        if self.road not in ROADS:
            raise ConfigError(f"highway road must be one of {', '.join(ROADS)}, got {self.road!r}")
        if not 0 < self.traffic_speed_min_mps <= self.traffic_speed_max_mps:
            raise ConfigError(
                "highway traffic speeds need 0 < traffic_speed_min_mps <= traffic_speed_max_mps"
            )


def parse_spec(spec: str) -> tuple[str, HighwayConfig]:
    """``highway-NAME[:key=value,...]`` -> (name, config); unknown names or keys are errors."""
    name, _, params = spec.partition(":")
    if name not in HIGHWAY_SCENARIOS:
        raise ConfigError(
            f"unknown scenario {name!r}; highway scenarios: {', '.join(HIGHWAY_SCENARIOS)}"
        )
    fields = {f.name: f for f in dataclasses.fields(HighwayConfig)}
    values: dict[str, Any] = {}  # each value of its field's type
    for item in filter(None, params.split(",")):
        key, eq, text = item.partition("=")
        key = key.strip().replace("-", "_")
        if not eq or key not in fields:
            raise ConfigError(
                f"scenario {name}: bad parameter {item!r}; expected key=value with key one of "
                f"{', '.join(fields)}"
            )
        kind = type(getattr(HighwayConfig(), key))
        try:
            values[key] = (
                text.strip().lower() in ("1", "true", "yes") if kind is bool else kind(text)
            )
        except ValueError:
            raise ConfigError(
                f"scenario {name}: {key} must be a {kind.__name__}, got {text!r}"
            ) from None
    return name, HighwayConfig(**values)


class HighwayScenario:
    """A ``Scenario`` (``openconvoy.envs.scenarios``) whose world includes highway-env
    traffic; ``world`` is rebuilt by every ``reset``. Run it in ``TrafficConvoyEnv``."""

    ROAD_START_M = 300.0
    """highway-env x of the leader's start (room behind the convoy for traffic)."""

    def __init__(
        self,
        name: str,
        presets: Sequence[VehiclePreset],
        config: HighwayConfig,
        spacing: SpacingConfig = CACC,
        origin: Origin = DEFAULT_ORIGIN,
    ) -> None:
        if len(presets) < 2:
            raise ConfigError("a convoy needs a leader and at least one follower")
        self.name = name
        self.config = config
        self.presets = tuple(presets)
        self.spacing = spacing
        self.origin = origin
        self.duration_s = config.duration_s
        self.convoy_lane = 1 if name != "highway-merge" else config.lanes - 1
        if name == "highway-cut-in" and not 1 <= config.cut_in_gap < len(self.presets):
            raise ConfigError(
                f"highway-cut-in: cut_in_gap must be 1..{len(self.presets) - 1} (a follower), "
                f"got {config.cut_in_gap}"
            )
        if name == "highway-lane-drop" and config.lanes < 3:
            raise ConfigError("highway-lane-drop needs lanes >= 3")
        self.frame = HighwayFrame(self.ROAD_START_M, self.convoy_lane * LANE_WIDTH_M)
        self.path: Path | None = straight_road(-self.ROAD_START_M, 3000.0)
        self.world: TrafficWorld | None = None
        self._t_last: float | None = None

    def with_changes(
        self,
        *,
        presets: Sequence[VehiclePreset] | None = None,
        spacing: SpacingConfig | None = None,
        origin: Origin | None = None,
    ) -> HighwayScenario:
        """A new scenario, built and validated again, with these parameters changed."""
        return HighwayScenario(
            self.name,
            self.presets if presets is None else presets,
            self.config,
            self.spacing if spacing is None else spacing,
            self.origin if origin is None else origin,
        )

    @property
    def n_vehicles(self) -> int:
        return len(self.presets)

    def _offsets(self) -> list[float]:
        sigma = SpacingPolicy(self.spacing)
        lengths = [p.length_m for p in self.presets]
        out = [0.0]
        for i in range(1, len(lengths)):
            out.append(out[-1] + sigma.pair_gap(self.config.speed_mps, lengths[i], lengths[i - 1]))
        return out

    def initial_state(self) -> InitialState:
        n = self.n_vehicles
        x = -np.array(self._offsets())
        return InitialState(x, np.zeros(n), np.zeros(n), np.full(n, self.config.speed_mps))

    def reset(self, rng: np.random.Generator) -> None:
        cfg = self.config
        self.world = TrafficWorld(
            self.frame,
            [p.length_m for p in self.presets],
            [p.width_m for p in self.presets],
            cfg.speed_mps,
        )
        road_rng = np.random.RandomState(int(rng.integers(2**31 - 1)))
        road = self._road(road_rng)
        traffic = _Spawner(road, road_rng, self).spawn()
        self.world.reset(road, traffic)
        self._t_last = None

    def leader_command(
        self, t: float, x: float, y: float, heading: float, speed: float
    ) -> tuple[float, float]:
        """highway-env's IDM acceleration turned into a speed setpoint for our first-order
        speed loop (``v + a * lag``), heading onto the lane's centre line (y = 0)."""
        lead = self.presets[0]
        assert self.world is not None, "reset() first"
        a = self.world.leader_idm_accel()
        v_cmd = max(0.0, speed + a * max(lead.speed_lag_s, 0.1))
        look = max(5.0, 1.0 * speed)
        return v_cmd, math.atan2(-y, look)

    # --- roads ---------------------------------------------------------------------------

    def _road(self, rs: np.random.RandomState) -> Road:
        cls = {"vector": VectorRoad, "fast": FastRoad, "highway-env": Road}[self.config.road]
        if self.name == "highway-merge":
            return self._merge_road(cls, rs)
        if self.name == "highway-lane-drop":
            return self._drop_road(cls, rs)
        net = RoadNetwork.straight_road_network(
            self.config.lanes, start=0.0, length=10000.0, speed_limit=40.0
        )
        return cls(network=net, np_random=rs)

    def _merge_road(self, cls: type, rs: np.random.RandomState) -> Road:
        """highway-env's ``MergeGenericEnv`` road, placed ``merge_at_m`` ahead of the leader."""
        lanes, cfg = self.config.lanes, self.config
        converge, parallel = 80.0, 80.0
        b = self.ROAD_START_M + cfg.merge_at_m
        pre = b - converge
        net = RoadNetwork()
        for nodes, start, length in (
            (("a", "b"), 0.0, b),
            (("b", "c"), b, parallel),
            (("c", "d"), b + parallel, 5000.0),
        ):
            RoadNetwork.straight_road_network(
                lanes, start=start, length=length, nodes_str=nodes, speed_limit=40.0, net=net
            )
        amplitude = 3.25
        y_par = lanes * LANE_WIDTH_M
        c = LineType.CONTINUOUS_LINE
        ljk = StraightLane(
            [0, y_par + 2 * amplitude],
            [pre, y_par + 2 * amplitude],
            line_types=[c, c],
            forbidden=True,
            speed_limit=40.0,
        )
        lkb = SineLane(
            [pre, y_par + amplitude],
            [b, y_par + amplitude],
            amplitude,
            2 * np.pi / (2 * converge),
            np.pi / 2,
            line_types=[c, c],
            forbidden=True,
            speed_limit=40.0,
        )
        lbc = StraightLane(
            [b, y_par],
            [b + parallel, y_par],
            line_types=[LineType.STRIPED, c],
            forbidden=True,
            speed_limit=40.0,
        )
        net.add_lane("j", "k", ljk)
        net.add_lane("k", "b", lkb)
        net.add_lane("b", "c", lbc)
        road = cls(network=net, np_random=rs, neighbour_vehicles_connected_lanes=True)
        road.objects.append(Obstacle(road, lbc.position(parallel, 0)))
        return road

    def _drop_road(self, cls: type, rs: np.random.RandomState) -> Road:
        """Three (or more) lanes; the right one ends ``drop_at_m`` ahead of the leader."""
        lanes = self.config.lanes
        drop = self.ROAD_START_M + self.config.drop_at_m
        net = RoadNetwork.straight_road_network(
            lanes, start=0.0, length=drop, nodes_str=("a", "b"), speed_limit=40.0
        )
        RoadNetwork.straight_road_network(
            lanes - 1, start=drop, length=5000.0, nodes_str=("b", "c"), speed_limit=40.0, net=net
        )
        road = cls(network=net, np_random=rs, neighbour_vehicles_connected_lanes=True)
        road.objects.append(Obstacle(road, net.get_lane(("a", "b", lanes - 1)).position(drop, 0)))
        return road


class _Spawner:
    """Places a scenario's traffic on a fresh road, randomized by ``rs``."""

    MIN_SPACING_M = 20.0

    def __init__(self, road: Road, rs: np.random.RandomState, scenario: HighwayScenario) -> None:
        self.road, self.rs, self.sc = road, rs, scenario
        self.cfg = scenario.config
        self.taken: dict[int, list[float]] = {}
        x0 = scenario.frame.x0
        # The convoy's span in its lane, with room at both ends.
        offsets = scenario._offsets()
        self.taken[scenario.convoy_lane] = [x0 - o for o in offsets]
        self.cars: list[IDMVehicle] = []

    def _free(self, lane: int, s: float) -> bool:
        return all(abs(s - o) > self.MIN_SPACING_M for o in self.taken.get(lane, []))

    def _add(self, v: IDMVehicle, lane: int, s: float) -> None:
        self.taken.setdefault(lane, []).append(s)
        self.cars.append(v)

    def _car(
        self, edge: tuple[str, str], lane: int, s: float, speed: float, target: float | None = None
    ) -> IDMVehicle:
        ln = self.road.network.get_lane((*edge, lane))
        v = IDMVehicle(
            self.road, ln.position(s, 0.0), ln.heading_at(s), speed, target_speed=target or speed
        )
        v.randomize_behavior()
        return v

    def spawn(self) -> list[IDMVehicle]:
        name, cfg, sc = self.sc.name, self.cfg, self.sc
        x0 = sc.frame.x0
        lanes = list(range(cfg.lanes))
        edge = ("0", "1")
        if name == "highway-cut-in":
            self._cut_in()
            lanes = [k for k in lanes if k != sc.convoy_lane]
        elif name == "highway-slow-traffic":
            for lane in range(cfg.lanes):
                s = x0 + cfg.slow_ahead_m + self.rs.uniform(0.0, 10.0)
                self._add(self._car(edge, lane, s, cfg.slow_speed_mps), lane, s)
        elif name == "highway-merge":
            edge = ("a", "b")
            self._merge()
        elif name == "highway-lane-drop":
            edge = ("a", "b")
            self._drop()
        lo, hi = cfg.traffic_speed_min_mps, cfg.traffic_speed_max_mps
        offsets_end = sc._offsets()[-1]
        half = max(250.0, 8.0 * cfg.traffic)  # metres each side of the leader's start
        if name == "highway-slow-traffic":
            lo, hi = 0.9 * cfg.slow_speed_mps, 1.1 * cfg.slow_speed_mps
        for _ in range(cfg.traffic):
            for _try in range(20):
                lane = int(self.rs.choice(lanes))
                s = float(self.rs.uniform(x0 - half, x0 + half))
                if name == "highway-slow-traffic":
                    s = float(
                        self.rs.uniform(x0 + cfg.slow_ahead_m + 30.0, x0 + cfg.slow_ahead_m + 400.0)
                    )
                if name == "highway-lane-drop":
                    s = min(s, x0 + cfg.drop_at_m - 60.0)
                if name == "highway-merge":
                    s = min(s, x0 + cfg.merge_at_m - 10.0)
                if lane == sc.convoy_lane and s > x0 and name != "highway-slow-traffic":
                    s += 150.0  # never right in front of the leader: the scenario says what is
                if name == "highway-cut-in" and lane == sc.convoy_lane - 1 and s > x0 - offsets_end:
                    s += 250.0  # nor in front of the cut-in car: it paces its gap until its cue
                if self._free(lane, s):
                    speed = float(self.rs.uniform(lo, hi))
                    self._add(self._car(edge, lane, s, speed), lane, s)
                    break
        return self.cars

    def _cut_in(self) -> None:
        cfg, sc = self.cfg, self.sc
        offsets = sc._offsets()
        g = cfg.cut_in_gap
        s = sc.frame.x0 - 0.5 * (offsets[g - 1] + offsets[g]) + cfg.cut_in_offset_m
        lane = sc.convoy_lane - 1
        speed = cfg.speed_mps if cfg.cut_in_speed_mps < 0 else cfg.cut_in_speed_mps
        ln = self.road.network.get_lane(("0", "1", lane))
        # Paces its gap at the convoy's speed until the cue, then cuts in at its own speed.
        schedule: list[tuple[float, int, float | None]] = [(cfg.cut_in_at_s, sc.convoy_lane, speed)]
        if cfg.cut_out_at_s >= 0:
            schedule.append((cfg.cut_out_at_s, lane, None))
        v = ScriptedLaneChanger(
            self.road,
            ln.position(s, 0.0),
            ln.heading_at(s),
            cfg.speed_mps,
            schedule,
            target_speed=cfg.speed_mps,
        )
        self._add(v, lane, s)

    def _merge(self) -> None:
        cfg, sc = self.cfg, self.sc
        speed = cfg.speed_mps
        b = sc.ROAD_START_M + cfg.merge_at_m
        t_lead = cfg.merge_at_m / speed  # when the leader reaches the merge (node b)
        for k in range(cfg.merge_cars):
            # Car k reaches b merge_offset_m ahead of the leader, the next ones 25 m apart.
            dist = speed * t_lead - cfg.merge_offset_m + 25.0 * k
            # The ramp runs straight from x = 0 to b - 80 m, then 80 m of sine to b.
            s = max(b - dist, 0.0)
            ramp = self.road.network.get_lane(("j", "k", 0))
            v = IDMVehicle(
                self.road, ramp.position(s, 0.0), ramp.heading_at(s), speed, target_speed=speed
            )
            self.cars.append(v)

    def _drop(self) -> None:
        """Cars in the ending lane: one 90 m ahead of the leader, one beside the convoy's middle."""
        cfg, sc = self.cfg, self.sc
        lane = cfg.lanes - 1
        x0 = sc.frame.x0
        for s in (x0 + 90.0, x0 - 0.5 * sc._offsets()[-1])[: cfg.drop_cars]:
            self._add(self._car(("a", "b"), lane, s, 0.95 * cfg.speed_mps, cfg.speed_mps), lane, s)


def make_highway_scenario(
    spec: str, n_followers: int | None = None, presets: Sequence[VehiclePreset] | None = None
) -> HighwayScenario:
    """A highway scenario by spec (``HIGHWAY_SCENARIOS``, optional ``:key=value,...``);
    ``n_followers`` default 2; ``presets`` (leader first) replace the full-size cars."""
    name, config = parse_spec(spec)
    if presets is not None:
        presets = tuple(presets)
        if n_followers is not None and n_followers != len(presets) - 1:
            raise ConfigError(
                f"n_followers={n_followers} but {len(presets)} vehicle presets (leader included)"
            )
    else:
        n = 2 if n_followers is None else int(n_followers)
        if n < 1:
            raise ConfigError(f"a convoy needs at least one follower, got n_followers={n}")
        presets = (CAR,) * (n + 1)
    return HighwayScenario(name, presets, config)
