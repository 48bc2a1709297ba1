"""The plant: kinematic bicycles with their autopilot inner loops, vectorized over vehicles.

Each vehicle takes a speed setpoint (m/s) and an absolute heading setpoint (rad, ENU).
After the preset's actuation delay, speed follows with a first-order lag clipped by the
acceleration limits, heading follows with a lag clipped by the turn-rate limit and by the
bicycle's maximum curvature at the current speed (no turning on the spot), and the
reference point moves along the heading. Matches shared/AUTOPILOTS.md's Rover response.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from openconvoy.core.state import VehicleState
from openconvoy.envs.vehicles import VehiclePreset


class BicyclePlant:
    """``n`` vehicles stepped together with a fixed time step ``dt`` (s)."""

    def __init__(self, presets: Sequence[VehiclePreset], dt: float) -> None:
        if dt <= 0:
            raise ValueError(f"plant time step must be positive, got {dt}")
        self.presets = list(presets)
        self.dt = dt
        n = len(self.presets)
        col = lambda attr: np.array([getattr(p, attr) for p in self.presets], dtype=float)  # noqa: E731
        self._tau_v = np.maximum(col("speed_lag_s"), 1e-6)
        self._tau_h = np.maximum(col("heading_lag_s"), 1e-6)
        self._acc = col("accel_max_mps2")
        self._dec = col("decel_max_mps2")
        self._rate = col("turn_rate_max_radps")
        self._vmax = col("max_speed_mps")
        self._kappa = np.tan(col("max_steer_rad")) / col("wheelbase_m")
        self._delay_steps = np.array(
            [int(round(p.actuation_delay_s / dt)) for p in self.presets], dtype=int
        )
        self._depth = int(self._delay_steps.max()) + 1 if n else 1
        self.x = np.zeros(n)
        self.y = np.zeros(n)
        self.heading = np.zeros(n)
        self.speed = np.zeros(n)
        self.accel = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        self._queue_v = np.zeros((self._depth, n))
        self._queue_h = np.zeros((self._depth, n))
        self._head = 0
        self._idx = np.arange(n)

    def __len__(self) -> int:
        return len(self.presets)

    def reset(
        self,
        x: np.ndarray,
        y: np.ndarray,
        heading: np.ndarray,
        speed: np.ndarray | None = None,
    ) -> None:
        """Place the vehicles; pending setpoints hold the initial speed and heading."""
        n = len(self)
        self.x = np.asarray(x, dtype=float).copy()
        self.y = np.asarray(y, dtype=float).copy()
        self.heading = np.asarray(heading, dtype=float).copy()
        self.speed = np.zeros(n) if speed is None else np.asarray(speed, dtype=float).copy()
        self.accel = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        self._queue_v[:] = self.speed
        self._queue_h[:] = self.heading
        self._head = 0

    def step(self, cmd_speed: np.ndarray, cmd_heading: np.ndarray) -> None:
        """Advance ``dt`` seconds with new setpoints (speed m/s, absolute heading rad)."""
        dt = self.dt
        self._queue_v[self._head] = cmd_speed
        self._queue_h[self._head] = cmd_heading
        slot = (self._head - self._delay_steps) % self._depth
        v_cmd = np.clip(self._queue_v[slot, self._idx], -self._vmax, self._vmax)
        h_cmd = self._queue_h[slot, self._idx]
        self._head = (self._head + 1) % self._depth

        # Speed: first-order lag, clipped to the acceleration limits.
        dv = np.clip((v_cmd - self.speed) / self._tau_v, -self._dec, self._acc) * dt
        # Never overshoot the setpoint within one step.
        dv = np.where(np.abs(dv) > np.abs(v_cmd - self.speed), v_cmd - self.speed, dv)
        v_new = self.speed + dv

        # Heading: lag towards the setpoint, clipped by turn rate and curvature at speed.
        err = (h_cmd - self.heading + math.pi) % (2.0 * math.pi) - math.pi
        v_mid = 0.5 * (self.speed + v_new)
        rate_cap = np.minimum(self._rate, np.abs(v_mid) * self._kappa)
        rate = np.clip(err / np.maximum(self._tau_h, dt), -rate_cap, rate_cap)
        h_mid = self.heading + 0.5 * rate * dt

        self.x = self.x + v_mid * np.cos(h_mid) * dt
        self.y = self.y + v_mid * np.sin(h_mid) * dt
        self.heading = (self.heading + rate * dt + math.pi) % (2.0 * math.pi) - math.pi
        self.accel = dv / dt
        self.yaw_rate = rate
        self.speed = v_new

    def state(self, i: int, t: float) -> VehicleState:
        """Vehicle ``i``'s state at time ``t`` (its id is its index)."""
        p = self.presets[i]
        return VehicleState(
            vehicle_id=i, t=t, x=float(self.x[i]), y=float(self.y[i]),
            speed=float(self.speed[i]), heading=float(self.heading[i]),
            accel=float(self.accel[i]), yaw_rate=float(self.yaw_rate[i]),
            length=p.length_m, width=p.width_m,
        )
