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

from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState
from openconvoy.envs.vehicles import VehiclePreset

SCALAR_MAX_VEHICLES = 8
"""Up to this many vehicles the step runs on Python floats: numpy's per-call overhead
dominates on a handful of elements (measured 47 µs vs 7.6 µs for the paper's 3 vehicles)."""


class BicyclePlant:
    """``n`` vehicles stepped together with a fixed time step ``dt`` (s).

    ``vectorized`` forces the numpy step (None: numpy above ``SCALAR_MAX_VEHICLES``);
    both steps compute the same equations.
    """

    def __init__(
        self, presets: Sequence[VehiclePreset], dt: float, vectorized: bool | None = None
    ) -> None:
        if dt <= 0:
            raise ConfigError(f"plant time step must be positive, got {dt}")
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
        self._vectorized = n > SCALAR_MAX_VEHICLES if vectorized is None else vectorized
        # The scalar step's copies of the parameters and of the setpoint queue.
        self._params = list(zip(
            self._tau_v.tolist(), self._tau_h.tolist(), self._acc.tolist(), self._dec.tolist(),
            self._rate.tolist(), self._vmax.tolist(), self._kappa.tolist(),
            self._delay_steps.tolist(),
        ))
        self._qv: list[list[float]] = [[0.0] * n for _ in range(self._depth)]
        self._qh: list[list[float]] = [[0.0] * n for _ in range(self._depth)]

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
        self._qv = [self.speed.tolist() for _ in range(self._depth)]
        self._qh = [self.heading.tolist() for _ in range(self._depth)]
        self._head = 0

    def step(self, cmd_speed: Sequence[float], cmd_heading: Sequence[float]) -> None:
        """Advance ``dt`` seconds with new setpoints (speed m/s, absolute heading rad)."""
        if not self._vectorized:
            self._step_scalar(cmd_speed, cmd_heading)
            return
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

    def _step_scalar(self, cmd_speed: Sequence[float], cmd_heading: Sequence[float]) -> None:
        """``step`` on Python floats, the same equations vehicle by vehicle."""
        dt, depth, head = self.dt, self._depth, self._head
        self._qv[head] = [float(v) for v in cmd_speed]
        self._qh[head] = [float(h) for h in cmd_heading]
        self._head = (head + 1) % depth
        two_pi, pi = 2.0 * math.pi, math.pi
        xs, ys, hs, vs = self.x.tolist(), self.y.tolist(), self.heading.tolist(), self.speed.tolist()
        acc_out, rate_out = [0.0] * len(vs), [0.0] * len(vs)
        for i, (tau_v, tau_h, acc, dec, rate_max, vmax, kappa, delay) in enumerate(self._params):
            slot = (head - delay) % depth
            v_cmd = min(max(self._qv[slot][i], -vmax), vmax)
            v = vs[i]
            dv = min(max((v_cmd - v) / tau_v, -dec), acc) * dt
            if abs(dv) > abs(v_cmd - v):  # never overshoot the setpoint within one step
                dv = v_cmd - v
            v_new = v + dv
            err = (self._qh[slot][i] - hs[i] + pi) % two_pi - pi
            v_mid = 0.5 * (v + v_new)
            cap = min(rate_max, abs(v_mid) * kappa)
            rate = min(max(err / max(tau_h, dt), -cap), cap)
            h_mid = hs[i] + 0.5 * rate * dt
            xs[i] += v_mid * math.cos(h_mid) * dt
            ys[i] += v_mid * math.sin(h_mid) * dt
            hs[i] = (hs[i] + rate * dt + pi) % two_pi - pi
            vs[i] = v_new
            acc_out[i] = dv / dt
            rate_out[i] = rate
        self.x, self.y, self.heading = np.array(xs), np.array(ys), np.array(hs)
        self.speed, self.accel, self.yaw_rate = np.array(vs), np.array(acc_out), np.array(rate_out)

    def state(self, i: int, t: float) -> VehicleState:
        """Vehicle ``i``'s state at time ``t`` (its id is its index)."""
        p = self.presets[i]
        return VehicleState(
            vehicle_id=i, t=t, x=float(self.x[i]), y=float(self.y[i]),
            speed=float(self.speed[i]), heading=float(self.heading[i]),
            accel=float(self.accel[i]), yaw_rate=float(self.yaw_rate[i]),
            length=p.length_m, width=p.width_m,
        )
