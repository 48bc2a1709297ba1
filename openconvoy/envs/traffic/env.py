"""TrafficConvoyEnv: ``ConvoyEnv`` with highway-env traffic around the convoy.

The member sequence (ladder, plant, own state, Tx, channel, Rx, observation), rewards,
infos and log rows are ``ConvoyEnv``'s; this class adds what traffic changes:

- after the plant moves, the world places the convoy on highway-env's road, steps the
  traffic, checks collisions and lets traffic decide (``TrafficWorld``);
- the forward ranging sensor sees the nearest vehicle in the path, convoy or traffic;
- a collision with traffic ends the episode like one inside the convoy (a follower's
  counts in its reward);
- log rows carry ``TRAFFIC_LOG_COLUMNS`` (ground truth, for ``core.metrics``'s traffic
  metrics), infos ``ahead_gap_m``, ``ahead_traffic``, ``traffic_collision``;
- ``render()`` draws highway-env's road, traffic and the convoy (coloured by mode) with
  highway-env's renderer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from openconvoy.core.errors import ConfigError
from openconvoy.envs.convoy_env import ConvoyEnv
from openconvoy.envs.render import MODE_COLOURS
from openconvoy.envs.traffic.scenarios import HighwayScenario, make_highway_scenario
from openconvoy.envs.traffic.world import InPath, TrafficWorld
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset
from openconvoy.envs.world import ConvoyWorld

TRAFFIC_LOG_COLUMNS: tuple[str, ...] = (
    "ahead_gap_m",
    "ahead_closing_mps",
    "ahead_length_m",
    "ahead_traffic",
    "traffic_collision",
)
"""Extra log columns, per vehicle per tick (ground truth): centre-to-centre distance to the
nearest vehicle in its path ahead, convoy or traffic (m; empty when none within 250 m);
how fast that gap shrinks (m/s, positive = closing); that vehicle's length (m); 1 if it is
traffic (no V2V), else 0; 1 once the vehicle has touched traffic (highway-env's rectangle
test), else 0."""


class TrafficConvoyWorld(ConvoyWorld):
    """``ConvoyWorld`` on highway-env's road: the traffic moves before every sense, the
    ranging sensor sees traffic too, and touching traffic ends the episode."""

    def __init__(self, scenario: HighwayScenario, *args: Any, **kwargs: Any) -> None:
        self.highway = scenario
        self.in_path: list[InPath | None] = []
        self.hits: list[bool] = []
        super().__init__(scenario, *args, **kwargs)

    @property
    def traffic(self) -> TrafficWorld:
        assert self.highway.world is not None, "reset() first"
        return self.highway.world

    def before_sense(self) -> None:
        world, p = self.traffic, self.plant
        world.place(p.x, p.y, p.heading, p.speed)
        if self.step_count > 0:
            world.step(self.dt)
        world.act(self.t)

    def measure(self) -> None:
        super().measure()
        self.in_path = self.traffic.in_path()
        self.hits = self.traffic.traffic_hits()
        self.collided = [c or h for c, h in zip(self.collided, self.hits[1:])]

    def terminated(self) -> bool:
        return any(self.collided) or self.hits[0]

    def ranging_readings(self) -> dict[int, tuple[float, float]]:
        """The forward sensor sees the nearest vehicle in the path (convoy or traffic)."""
        seen = []
        for i, sensor in self.ranging_sensors:
            target = self.in_path[i]
            if target is not None and target.range_m <= sensor.max_range_m:
                seen.append((i, sensor, target))
        if not seen:
            return {}
        # One draw for all (the same numbers, in the same order, as one draw per sensor).
        noise = self._ranging_rng.normal(size=(len(seen), 2)).tolist()
        return {
            i: (
                target.range_m + sensor.range_noise_m * n1,
                target.range_rate_mps + sensor.range_rate_noise_mps * n2,
            )
            for (i, sensor, target), (n1, n2) in zip(seen, noise)
        }

    def extra_columns(self) -> dict[str, list[Any]]:
        values = [_ahead_values(a) + (1.0 if h else 0.0,) for a, h in zip(self.in_path, self.hits)]
        return {c: [v[k] for v in values] for k, c in enumerate(TRAFFIC_LOG_COLUMNS)}


class TrafficConvoyEnv(ConvoyEnv):
    """The convoy on a highway with traffic (PettingZoo ``ParallelEnv``, followers are the
    agents). ``scenario``: a highway spec (``openconvoy.envs.traffic.scenarios``) or a
    ``HighwayScenario``; every other argument is ``ConvoyEnv``'s."""

    metadata = {**ConvoyEnv.metadata, "name": "openconvoy_traffic_v0", "render_fps": 20}
    LOG_EXTRA_COLUMNS = TRAFFIC_LOG_COLUMNS
    WORLD = TrafficConvoyWorld

    def __init__(
        self,
        scenario: str | HighwayScenario = "highway-cut-in",
        n_followers: int | None = None,
        vehicle_presets: Sequence[VehiclePreset | str] | None = None,
        **kwargs: Any,
    ) -> None:
        if isinstance(scenario, str):
            presets = None
            if vehicle_presets is not None:
                presets = [
                    p if isinstance(p, VehiclePreset) else vehicle_preset(p)
                    for p in vehicle_presets
                ]
            scenario = make_highway_scenario(scenario, n_followers, presets)
        elif not isinstance(scenario, HighwayScenario):
            raise ConfigError(
                "TrafficConvoyEnv runs highway scenarios (a spec or a HighwayScenario)"
            )
        elif n_followers is not None or vehicle_presets is not None:
            raise ConfigError(
                "n_followers and vehicle_presets apply to scenario specs, not Scenario objects"
            )
        super().__init__(scenario, **kwargs)

    @property
    def world(self) -> TrafficWorld:
        """The traffic world of the current episode (rebuilt by ``reset``)."""
        sim = self.sim
        assert isinstance(sim, TrafficConvoyWorld)
        return sim.traffic

    def _infos(self) -> dict[str, dict[str, Any]]:
        infos = super()._infos()
        sim = self.sim
        assert isinstance(sim, TrafficConvoyWorld)
        for i, a in enumerate(self.agents, start=1):
            target = sim.in_path[i]
            infos[a]["ahead_gap_m"] = None if target is None else target.range_m
            infos[a]["ahead_traffic"] = None if target is None else target.is_traffic
            infos[a]["traffic_collision"] = sim.hits[i]
        return infos

    # --- rendering --------------------------------------------------------------------------

    def render(self) -> np.ndarray | None:
        """``rgb_array``: highway-env's picture of the road around the convoy, H x W x 3."""
        if self.render_mode is None:
            return super().render()
        from openconvoy.envs.traffic.render import draw_highway

        modes = ["leader", *self.sim.modes[1:]]
        for v, mode in zip(self.world.convoy, modes):
            v.color = MODE_COLOURS.get(mode, (0, 0, 0))
        return draw_highway(self.world)


def _ahead_values(a: InPath | None) -> tuple[float, float, float, float]:
    if a is None:
        return (math.nan, math.nan, math.nan, math.nan)
    return (a.range_m, -a.range_rate_mps, a.length_m, 1.0 if a.is_traffic else 0.0)
