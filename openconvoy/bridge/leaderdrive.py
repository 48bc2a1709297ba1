"""The deploy runner's leader driving and run length.

A scenario-driven leader follows its scenario's (or track's) speed profile with the same
heading controller as the simulated leader; a passive one commands nothing. When the run's
duration is over, that leader brakes to rest while still broadcasting (its followers see it
stop and stop behind it), then the run ends; every other vehicle ends at once.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import numpy as np

from openconvoy.bridge.link import Telemetry
from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.plans import Plan, leader_plan
from openconvoy.core.state import VehicleState, wrap_angle

FINISH_TIMEOUT_S = 10.0
"""Longest a leader brakes after its scenario before ending the run anyway (s)."""
AT_REST_MPS = 0.05
"""A braking leader is at rest below this speed (m/s)."""


class LeaderDriver(Protocol):
    """The leader's driver (``envs.scenarios.Scenario`` has this method)."""

    duration_s: float

    def leader_command(
        self, t: float, x: float, y: float, heading: float, speed: float
    ) -> tuple[float, float]: ...


class LeaderDriving:
    """What the leader commands, and when a run is over.

    Args:
        driver: the leader's scenario or track (None: passive, or a follower).
        is_leader: vehicle 0; passive: a person drives the leader.
        commanding: setpoints are sent (not dry-run, not passive).
        duration_s: ``--duration`` (s); None = the driver's duration for a driven leader.
        rate_hz: control rate (Hz): half a period of slack on the duration.
        origin: the geodetic origin of the driver's frame when it differs from the
            convoy's (track files carry their own); None = the convoy's.
        preset: the leader's vehicle preset (``envs.vehicles.VehiclePreset``), the model
            its shared plan predicts with; None = it shares no plan.
    """

    def __init__(
        self,
        driver: LeaderDriver | None,
        *,
        is_leader: bool,
        passive: bool,
        commanding: bool,
        duration_s: float | None,
        rate_hz: float,
        origin: Origin | None = None,
        preset: Any = None,
    ) -> None:
        self.driver = driver
        self.is_leader = is_leader
        self.passive = passive
        self.commanding = commanding
        self.duration_option_s = duration_s
        self.rate_hz = rate_hz
        self.origin = origin
        self.preset = preset
        self.t_finish: float | None = None
        """Monotonic time (s) a leader's scenario ended and it began braking; None before."""

    def reset(self, seed: int) -> None:
        """Seed the driver's randomness (drivers that have any: ``reset(rng)``)."""
        if self.driver is not None and hasattr(self.driver, "reset"):
            self.driver.reset(np.random.default_rng(seed))

    def duration_s(self) -> float | None:
        """How long the run drives after the convoy started (s); None = until stopped."""
        if self.duration_option_s is not None:
            return self.duration_option_s
        if self.is_leader and self.driver is not None and not self.passive:
            return float(self.driver.duration_s)
        return None

    def command(
        self, tel: Telemetry, own: VehicleState, now: float, t_start: float
    ) -> tuple[float, float, str, str]:
        """The leader's (speed m/s, heading change rad, mode, "") at monotonic ``now``."""
        if self.t_finish is not None:
            # Scenario over: brake to rest while still broadcasting, so the followers see
            # their leader stop and stop behind it.
            return 0.0, 0.0, "stop", ""
        if self.passive or self.driver is None:
            return 0.0, 0.0, "coop", ""
        x, y = own.x, own.y
        if self.origin is not None:
            ex, ey, _ = geodetic_to_enu(self.origin, tel.lat_deg, tel.lon_deg)
            x, y = float(ex), float(ey)
        speed, heading = self.driver.leader_command(
            now - t_start, float(x), float(y), own.heading, own.speed
        )
        return float(speed), wrap_angle(float(heading) - own.heading), "coop", ""

    def plan(
        self, own: VehicleState, now: float, t_start: float | None, wall: float, mpc: Any
    ) -> Plan | None:
        """The plan a driven leader shares at monotonic ``now`` (s), stamped with ``wall``
        (s, the shared clock): its driver's speed profile ahead through its speed lag
        (``core.plans.leader_plan``, as the simulated leader's), over ``mpc``'s horizon and
        step (the followers' MPC config); None while it waits to start, after its scenario
        (it brakes: ``core.plans.braking_plan``), passive, or for a driver without a speed
        profile."""
        if (
            self.passive
            or self.driver is None
            or t_start is None
            or self.t_finish is not None
            or self.preset is None
            or mpc is None
        ):
            return None
        plan = leader_plan(
            self.driver, self.preset, now - t_start, own.speed, mpc.horizon, mpc.step_s
        )
        # The driver's clock is the run's (monotonic, from the start); receivers read wall.
        return None if plan is None else dataclasses.replace(plan, t0=wall)

    def over(self, now: float, t_start: float, speed: float) -> bool:
        """Whether the run's duration is over at ``now`` (a scenario-driven leader first
        brakes to rest: ``t_finish`` is set, and it is over once at rest or after
        ``FINISH_TIMEOUT_S``)."""
        limit = self.duration_s()
        # Half a period of slack: tick times are sums of floats.
        if limit is None or now - t_start < limit - 0.5 / self.rate_hz:
            return False
        if not self.brakes_at_end:
            return True
        if self.t_finish is None:
            self.t_finish = now
            return False
        return abs(speed) < AT_REST_MPS or now - self.t_finish > FINISH_TIMEOUT_S

    @property
    def brakes_at_end(self) -> bool:
        """A scenario-driven leader brakes to rest before ending; others end at once."""
        return self.is_leader and self.commanding and self.driver is not None
