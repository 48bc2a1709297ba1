"""Scenarios: who drives, where they start, and what the leader does.

``Scenario`` is the seam between ``ConvoyEnv`` and whatever generates the world: the
built-in scenarios below (DESIGN.md, Scenarios) drive the leader along a ``Path`` with a
speed profile; traffic simulators (highway-env) can implement the same protocol later.

Built-in scenarios, any number of followers (``make_scenario(spec, n_followers)``):

- ``paper``: straight road east, leader + n followers (presets alternating 1/10, 1/6,
  1/10, ...), desired gap 15 m, starting at rest at the desired gaps; leader speed
  1 m/s for 20 s, 2 m/s for 20 s, 1 m/s for 20 s, the setpoint ramped at the leader's
  acceleration limit. 60 s.
- ``track``: a closed oval (two straights and two semicircles of radius 10 m),
  counter-clockwise at 1.5 m/s, starting at rest 15 m apart on the bottom straight (the
  straights are 20 m, or as long as the convoy plus 5 m, or longer so the convoy takes at
  most two thirds of the loop). Two laps.
- ``emergency-braking``: full-size cars (three by default) on a straight road at 25 m/s,
  spaced for CACC (2 m standstill between bumpers + 0.6 s headway, as
  ``core.spacing``'s constant-time-headway computes it); after 5 s the
  leader brakes at 6 m/s² to a stop. 15 s.
- ``track-file:PATH``: the leader follows a track file in the original OpenConvoy JSON
  format (see ``openconvoy.envs.track``) at the file's segment speeds; vehicles start at
  rest 15 m apart, the last one at the track's start (the first straight's start point)
  on a closed track, the leader there on an open one (followers behind it, on the
  extension of the first straight). Two laps when closed, else until the end of the
  track.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from openconvoy.comms.geodesy import Origin
from openconvoy.core.errors import ConfigError
from openconvoy.core.spacing import SpacingConfig, SpacingPolicy
from openconvoy.envs.path import Path, oval, straight_road
from openconvoy.envs.track import Track, example_track_path, load_track
from openconvoy.envs.vehicles import VEHICLE_PRESETS, VehiclePreset

#: The convoy origin of the synthetic scenarios (an open field; only the log's lat/lon use it).
DEFAULT_ORIGIN = Origin(28.6024, -81.2001, 0.0)

SCENARIO_NAMES: tuple[str, ...] = ("paper", "track", "emergency-braking", "track-file:PATH")
TRAFFIC_PREFIX = "highway-"
"""Specs starting with this are highway scenarios with traffic
(``openconvoy.envs.traffic.scenarios``, the ``traffic`` extra)."""


def is_traffic_scenario(scenario: str | Scenario) -> bool:
    """Is ``scenario`` (a spec or a Scenario) a highway scenario with traffic?"""
    name = scenario if isinstance(scenario, str) else scenario.name
    return name.startswith(TRAFFIC_PREFIX)


@dataclass(frozen=True)
class InitialState:
    """Initial plant state for every vehicle (index 0 = leader): ENU metres, rad, m/s."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    speed: np.ndarray


@runtime_checkable
class Scenario(Protocol):
    """What ``ConvoyEnv`` needs from a scenario.

    Attributes:
        name: the spec it was made from.
        presets: one vehicle preset per vehicle, leader first.
        origin: the convoy origin (geodetic) of the local ENU frame.
        duration_s: episode length, seconds.
        spacing: default spacing policy σ (places the vehicles at its desired gaps and is
            the default member configuration's).
        path: the road the leader follows (for drawing and placement), or None.
    """

    name: str
    presets: tuple[VehiclePreset, ...]
    origin: Origin
    duration_s: float
    spacing: SpacingConfig

    @property
    def path(self) -> Path | None: ...  # read-only: a scenario's road may be a ``Path``

    @property
    def n_vehicles(self) -> int: ...

    def initial_state(self) -> InitialState:
        """Where the vehicles start."""

    def reset(self, rng: np.random.Generator) -> None:
        """Start a new episode (the leader's driver state; randomness from ``rng``)."""

    def leader_command(
        self, t: float, x: float, y: float, heading: float, speed: float
    ) -> tuple[float, float]:
        """The leader's setpoints at time ``t`` (s) given its state: (speed m/s, absolute
        heading rad)."""

    def with_changes(
        self,
        *,
        presets: Sequence[VehiclePreset] | None = None,
        spacing: SpacingConfig | None = None,
        origin: Origin | None = None,
    ) -> Scenario:
        """A new scenario, built and validated again, with these parameters changed (a
        built scenario is never modified)."""


SpeedProfile = Callable[[float, float], float]
"""Target leader speed (m/s) as a function of (time s, arc length m)."""


class PathScenario:
    """A scenario whose leader follows ``path`` at ``speed_profile(t, s)``.

    The leader's driver: the speed setpoint moves towards the profile at most at
    ``ramp_accel_mps2`` / ``ramp_decel_mps2`` (the leader's limits, so the setpoint is one
    the vehicle can track), and stops at the end of an open path; the heading setpoint
    points at the path point one look-ahead distance ahead (pure pursuit), with the
    look-ahead ``max(lookahead_min_m, lookahead_time_s * speed)``.
    """

    def __init__(
        self,
        name: str,
        presets: Sequence[VehiclePreset],
        path: Path,
        speed_profile: SpeedProfile,
        duration_s: float,
        spacing: SpacingConfig,
        start_speed_mps: float = 0.0,
        leader_start_s: float = 0.0,
        origin: Origin = DEFAULT_ORIGIN,
        lookahead_min_m: float = 1.5,
        lookahead_time_s: float = 1.0,
        ramp_accel_mps2: float | None = None,
        ramp_decel_mps2: float | None = None,
    ) -> None:
        if len(presets) < 1:
            raise ConfigError("a scenario needs at least the leader")
        self.name = name
        self.presets = tuple(presets)
        self.path = path
        self.speed_profile = speed_profile
        self.duration_s = float(duration_s)
        self.spacing = spacing
        self.origin = origin
        self.start_speed_mps = start_speed_mps
        self.leader_start_s = leader_start_s
        self.lookahead_min_m = lookahead_min_m
        self.lookahead_time_s = lookahead_time_s
        self._ramps = (ramp_accel_mps2, ramp_decel_mps2)
        lead = self.presets[0]
        self.ramp_accel_mps2 = ramp_accel_mps2 or lead.accel_max_mps2
        self.ramp_decel_mps2 = ramp_decel_mps2 or lead.decel_max_mps2
        if path.closed and self._offsets()[-1] > path.length:
            raise ConfigError(
                f"scenario {name!r}: {len(self.presets)} vehicles at the desired gaps do not fit "
                f"on a closed track of {path.length:.1f} m"
            )
        self.reset(np.random.default_rng(0))

    @property
    def n_vehicles(self) -> int:
        return len(self.presets)

    def with_changes(
        self,
        *,
        presets: Sequence[VehiclePreset] | None = None,
        spacing: SpacingConfig | None = None,
        origin: Origin | None = None,
    ) -> PathScenario:
        """See ``Scenario.with_changes``."""
        return PathScenario(
            self.name,
            self.presets if presets is None else presets,
            self.path,
            self.speed_profile,
            self.duration_s,
            self.spacing if spacing is None else spacing,
            self.start_speed_mps,
            self.leader_start_s,
            self.origin if origin is None else origin,
            self.lookahead_min_m,
            self.lookahead_time_s,
            *self._ramps,
        )

    def _offsets(self) -> list[float]:
        """Arc length behind the leader of each vehicle at the desired gaps, metres."""
        sigma = SpacingPolicy(self.spacing)
        lengths = [p.length_m for p in self.presets]
        out = [0.0]
        for i in range(1, len(lengths)):
            out.append(out[-1] + sigma.pair_gap(self.start_speed_mps, lengths[i], lengths[i - 1]))
        return out

    def initial_state(self) -> InitialState:
        n = self.n_vehicles
        xs, ys, hs = np.zeros(n), np.zeros(n), np.zeros(n)
        for i, back in enumerate(self._offsets()):
            s = self.leader_start_s - back
            if self.path.closed:
                s %= self.path.length
            xs[i], ys[i] = self.path.point_at(s)
            # Heading at the start of an open path's extension is its first segment's.
            hs[i] = self.path.heading_at(s)
        return InitialState(xs, ys, hs, np.full(n, float(self.start_speed_mps)))

    def reset(self, rng: np.random.Generator) -> None:
        self._s = (
            self.leader_start_s % self.path.length if self.path.closed else self.leader_start_s
        )
        self._cmd_speed = float(self.start_speed_mps)
        self._t_last: float | None = None

    def leader_command(
        self, t: float, x: float, y: float, heading: float, speed: float
    ) -> tuple[float, float]:
        path = self.path
        self._s = path.project(x, y, self._s)
        target = self.speed_profile(t, self._s)
        if not path.closed:
            # Stop at the end of an open road, braking at the leader's limit.
            remaining = max(path.length - self._s, 0.0)
            target = min(target, math.sqrt(2.0 * self.ramp_decel_mps2 * remaining))
        dt = 0.0 if self._t_last is None else max(t - self._t_last, 0.0)
        self._t_last = t
        if dt > 0.0:
            dv = target - self._cmd_speed
            self._cmd_speed += min(max(dv, -self.ramp_decel_mps2 * dt), self.ramp_accel_mps2 * dt)
        look = max(self.lookahead_min_m, self.lookahead_time_s * max(speed, 0.0))
        tx, ty = path.point_at(path.advance(self._s, look))
        return self._cmd_speed, math.atan2(ty - y, tx - x)


def _alternating_small(n_vehicles: int) -> tuple[VehiclePreset, ...]:
    small = (VEHICLE_PRESETS["1/10"], VEHICLE_PRESETS["1/6"])
    return tuple(small[i % 2] for i in range(n_vehicles))


def paper_speed(t: float, s: float) -> float:
    """The paper's leader speed profile: 1 m/s, 2 m/s from 20 s, 1 m/s from 40 s."""
    return 2.0 if 20.0 <= t < 40.0 else 1.0


PAPER_PHASES: tuple[tuple[float, float, float], ...] = (
    (0.0, 20.0, 1.0),
    (20.0, 40.0, 2.0),
    (40.0, 60.0, 1.0),
)
"""The paper scenario's speed phases: (start s, end s, leader speed m/s)."""


PAPER_GAP_M = 15.0
TRACK_GAP_M = 15.0


def paper_scenario(
    n_followers: int = 2, presets: Sequence[VehiclePreset] | None = None
) -> PathScenario:
    """DESIGN.md's ``paper`` scenario with ``n_followers`` followers."""
    spacing = SpacingConfig("constant-distance", distance_m=PAPER_GAP_M)
    n = n_followers + 1
    back = PAPER_GAP_M * n + 50.0
    road = straight_road(-back, 300.0)
    return PathScenario(
        "paper",
        presets or _alternating_small(n),
        road,
        paper_speed,
        duration_s=60.0,
        spacing=spacing,
        leader_start_s=back,
    )


def track_scenario(
    n_followers: int = 2,
    presets: Sequence[VehiclePreset] | None = None,
    radius_m: float = 10.0,
    speed_mps: float = 1.5,
    straight_m: float = 20.0,
) -> PathScenario:
    """DESIGN.md's ``track``: an oval of two straights and two semicircles at 1.5 m/s."""
    spacing = SpacingConfig("constant-distance", distance_m=TRACK_GAP_M)
    n = n_followers + 1
    # Lengthen the straights so the convoy starts on one (followers steer on their
    # predecessors' trails, which do not exist yet at the start: a straight start is
    # what a lab does) and takes at most two thirds of the loop.
    need = 1.5 * TRACK_GAP_M * n
    straight_m = max(
        straight_m, TRACK_GAP_M * n_followers + 5.0, (need - 2 * math.pi * radius_m) / 2.0
    )
    path = oval(straight_m, radius_m)
    laps = 2.0
    duration = laps * path.length / speed_mps + 5.0
    return PathScenario(
        "track",
        presets or _alternating_small(n),
        path,
        lambda t, s: speed_mps,
        duration_s=duration,
        spacing=spacing,
        leader_start_s=TRACK_GAP_M * n_followers + 2.5,
    )


EMERGENCY_BRAKE_AT_S = 5.0
EMERGENCY_DECEL_MPS2 = 6.0
EMERGENCY_SPEED_MPS = 25.0


def emergency_speed(t: float, s: float) -> float:
    """25 m/s, then from 5 s braking at 6 m/s² to a stop."""
    if t < EMERGENCY_BRAKE_AT_S:
        return EMERGENCY_SPEED_MPS
    return max(0.0, EMERGENCY_SPEED_MPS - EMERGENCY_DECEL_MPS2 * (t - EMERGENCY_BRAKE_AT_S))


def emergency_braking_scenario(
    n_followers: int = 2, presets: Sequence[VehiclePreset] | None = None
) -> PathScenario:
    """DESIGN.md's ``emergency-braking``: full-size cars, CACC spacing, hard stop."""
    spacing = SpacingConfig("constant-time-headway", standstill_m=2.0, headway_s=0.6)
    n = n_followers + 1
    back = 30.0 * n + 100.0
    road = straight_road(-back, 1000.0)
    return PathScenario(
        "emergency-braking",
        presets or (VEHICLE_PRESETS["full-size"],) * n,
        road,
        emergency_speed,
        duration_s=15.0,
        spacing=spacing,
        start_speed_mps=EMERGENCY_SPEED_MPS,
        leader_start_s=back,
        lookahead_min_m=5.0,
        lookahead_time_s=1.0,
        # The profile itself is the braking law; ramp limits only guard against steps.
        ramp_accel_mps2=VEHICLE_PRESETS["full-size"].accel_max_mps2,
        ramp_decel_mps2=EMERGENCY_DECEL_MPS2,
    )


def track_file_scenario(
    path: str,
    n_followers: int = 2,
    presets: Sequence[VehiclePreset] | None = None,
    gap_m: float = TRACK_GAP_M,
) -> PathScenario:
    """A leader following a track file (original OpenConvoy JSON) at its segment speeds."""
    track: Track = load_track(path)
    spacing = SpacingConfig("constant-distance", distance_m=gap_m)
    n = n_followers + 1
    if track.path.closed:
        vmin = float(np.min(track.speed_mps))
        duration = 2.0 * track.path.length / max(vmin, 0.1) + 5.0
    else:
        vmin = float(np.min(track.speed_mps))
        duration = track.path.length / max(vmin, 0.1) + 10.0
    return PathScenario(
        f"track-file:{path}",
        presets or _alternating_small(n),
        track.path,
        lambda t, s: track.speed_at(s),
        duration_s=duration,
        spacing=spacing,
        origin=track.origin,
        leader_start_s=gap_m * n_followers if track.path.closed else 0.0,
    )


def make_scenario(
    spec: str = "paper",
    n_followers: int | None = None,
    presets: Sequence[VehiclePreset] | None = None,
) -> Scenario:
    """A built-in scenario by spec (see ``SCENARIO_NAMES``), ``n_followers`` default 2.

    ``presets`` (leader first) replaces the scenario's vehicles and sets the convoy size.
    ``track-file:example`` loads the example track shipped with the package; ``highway-*``
    specs make ``traffic.scenarios.HighwayScenario`` objects (the ``traffic`` extra).
    """
    if presets is not None:
        presets = tuple(presets)
        if n_followers is not None and n_followers != len(presets) - 1:
            raise ConfigError(
                f"n_followers={n_followers} but {len(presets)} vehicle presets (leader included)"
            )
        n_followers = len(presets) - 1
    n = 2 if n_followers is None else int(n_followers)
    if n < 1:
        raise ConfigError(f"a convoy needs at least one follower, got n_followers={n}")
    if spec == "paper":
        return paper_scenario(n, presets)
    if spec == "track":
        return track_scenario(n, presets)
    if spec == "emergency-braking":
        return emergency_braking_scenario(n, presets)
    if is_traffic_scenario(spec):
        from openconvoy.envs.traffic.scenarios import make_highway_scenario  # needs [traffic]

        return make_highway_scenario(spec, n, presets)
    if spec.startswith("track-file:"):
        file = spec.split(":", 1)[1]
        if not file.strip():
            raise ConfigError(
                "scenario 'track-file:' needs a path: track-file:PATH (or track-file:example)"
            )
        if file == "example":
            file = str(example_track_path())
        return track_file_scenario(file, n, presets)
    raise ConfigError(
        f"unknown scenario {spec!r}; expected one of {', '.join(SCENARIO_NAMES)} or highway-*"
    )
