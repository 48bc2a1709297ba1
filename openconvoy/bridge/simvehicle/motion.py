"""How a simulated vehicle moves: the physics under a simulated autopilot's outputs.

Two vehicle models from the firmware test benches the recordings in shared/sitl and
shared/sitl-px4 were made with, plus the project's plant:

- ``SitlRover``: ArduPilot SITL's ``--model rover`` (``libraries/SITL/SIM_Rover.cpp``):
  throttle and steering servo outputs (−1…1) drive a car whose speed relaxes to
  ``throttle · max_speed`` at ``max_accel / max_speed`` per second (so 1500 + 25·v µs of
  throttle holds v m/s and a rover with throttle 0 coasts with a 2 s time constant) and
  whose yaw rate is speed over the turning circle of the steering angle.
- ``SihRover``: PX4 SIH's Ackermann rover (airframe 10045): 400 N · throttle against
  static/kinetic friction (μ 0.5/0.3 on 20 kg, hence the start-up dead zone below
  ~0.75 m/s) and a quadratic drag applied per ECEF axis (so the steady speed for a
  throttle depends on the direction of travel and the home location), bicycle steering
  with a 30° lock on a 0.321 m wheelbase.
- ``PresetMotion``: the simulator's ``envs.plant.BicyclePlant`` with a vehicle preset,
  driven by (speed, heading) targets instead of servo outputs.

All share ``MotionState``: NED positions (m) around home, NED yaw (rad, clockwise from
north), forward speed (m/s, negative when reversing) and NED yaw rate (rad/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.vehicles import VehiclePreset

GRAVITY = 9.80665


@dataclass
class MotionState:
    """Where a vehicle is and how it moves (NED, SI units). ``yaw_bias``: the estimator's
    heading error (rad): the autopilot reports and steers ``yaw + yaw_bias`` (PX4's EKF,
    shared/sitl-px4/README.md §4); position and velocity are true (GPS-aided)."""

    north: float = 0.0
    east: float = 0.0
    yaw: float = 0.0
    speed: float = 0.0
    yaw_rate: float = 0.0
    accel: float = 0.0
    yaw_bias: float = 0.0

    @property
    def estimated_yaw(self) -> float:
        """The yaw the autopilot believes (rad, NED)."""
        return wrap_pi(self.yaw + self.yaw_bias)


def wrap_pi(a: float) -> float:
    """Wrap an angle to [−π, π)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class SitlRover:
    """ArduPilot SITL's rover physics (ackermann, not skid-steered).

    ``step(throttle, steering, dt)`` with both in −1…1 as the servo outputs
    (pwm − 1500) / 500; positive steering turns right (clockwise)."""

    def __init__(
        self,
        state: MotionState,
        max_speed: float = 20.0,
        max_accel: float = 10.0,
        turning_circle_m: float = 1.8,
        max_wheel_turn_deg: float = 35.0,
    ) -> None:
        self.state = state
        self.max_speed = max_speed
        self.max_accel = max_accel
        self.turning_circle_m = turning_circle_m
        self._sin_max = math.sin(math.radians(max_wheel_turn_deg))
        self._max_turn = math.radians(max_wheel_turn_deg)

    def yaw_rate_for(self, steering: float, speed: float) -> float:
        """NED yaw rate (rad/s) for a steering output at a forward speed."""
        if abs(steering) < 1e-6 or abs(speed) < 1e-6:
            return 0.0
        diameter = self.turning_circle_m * self._sin_max / math.sin(steering * self._max_turn)
        return 2.0 * speed / diameter

    def step(self, throttle: float, steering: float, dt: float) -> None:
        s = self.state
        rate = self.yaw_rate_for(steering, s.speed)
        accel = self.max_accel * (throttle * self.max_speed - s.speed) / self.max_speed
        yaw_mid = s.yaw + 0.5 * rate * dt
        v_mid = s.speed + 0.5 * accel * dt
        s.north += v_mid * math.cos(yaw_mid) * dt
        s.east += v_mid * math.sin(yaw_mid) * dt
        s.yaw = wrap_pi(s.yaw + rate * dt)
        s.speed += accel * dt
        s.yaw_rate = rate
        s.accel = accel


class SihRover:
    """PX4 SIH's Ackermann rover (``src/modules/simulation/simulator_sih``, vehicle type 5).

    ``step(throttle, steering, dt)``: throttle −1…1 (force 400 N at 1), steering −1…1 of
    the 30° lock (positive = right). ``lat_deg``/``lon_deg`` place the ECEF axes on which
    SIH applies its drag per component."""

    MASS_KG = 20.0
    THRUST_N = 400.0
    MU_STATIC = 0.5
    MU_KINETIC = 0.3
    DRAG_PER_AXIS = 50.7  # N/(m/s)² on each ECEF velocity component, fitted to the table
    WHEELBASE_M = 0.321
    MAX_STEER_RAD = math.radians(30.0)

    def __init__(self, state: MotionState, lat_deg: float, lon_deg: float) -> None:
        self.state = state
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        # Unit ECEF vectors of local north and east.
        self._n = (-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat))
        self._e = (-math.sin(lon), math.cos(lon), 0.0)

    def drag_along(self, yaw: float, speed: float) -> float:
        """Drag force (N) against a forward speed along NED yaw, from SIH's per-axis drag."""
        cn, ce = math.cos(yaw), math.sin(yaw)
        force = 0.0
        for i in range(3):
            u = cn * self._n[i] + ce * self._e[i]  # ECEF component of the unit direction
            v = speed * u
            force += self.DRAG_PER_AXIS * math.copysign(v * v, v) * u
        return force

    def step(self, throttle: float, steering: float, dt: float) -> None:
        s = self.state
        m = self.MASS_KG
        force = self.THRUST_N * max(-1.0, min(1.0, throttle)) - self.drag_along(s.yaw, s.speed)
        if abs(s.speed) < 1e-3:
            if abs(force) <= self.MU_STATIC * m * GRAVITY:
                s.speed, s.yaw_rate, s.accel = 0.0, 0.0, 0.0
                return
            force -= math.copysign(self.MU_KINETIC * m * GRAVITY, force)
            new_speed = s.speed + force / m * dt
        else:
            friction = math.copysign(self.MU_KINETIC * m * GRAVITY, s.speed)
            new_speed = s.speed + (force - friction) / m * dt
            if new_speed * s.speed < 0 and abs(force) <= self.MU_STATIC * m * GRAVITY:
                new_speed = 0.0  # friction stops it; it does not push it backwards
        delta = max(-1.0, min(1.0, steering)) * self.MAX_STEER_RAD
        v_mid = 0.5 * (s.speed + new_speed)
        rate = v_mid * math.tan(delta) / self.WHEELBASE_M
        yaw_mid = s.yaw + 0.5 * rate * dt
        s.north += v_mid * math.cos(yaw_mid) * dt
        s.east += v_mid * math.sin(yaw_mid) * dt
        s.yaw = wrap_pi(s.yaw + rate * dt)
        s.accel = (new_speed - s.speed) / dt
        s.speed = new_speed
        s.yaw_rate = rate


class PresetMotion:
    """The simulator's plant with one vehicle preset, driven by targets:
    ``drive(speed, yaw_ned, dt)``. The preset's own loops (lag, limits, delay) act."""

    def __init__(self, state: MotionState, preset: VehiclePreset, dt: float) -> None:
        self.state = state
        self.preset = preset
        self._plant = BicyclePlant([preset], dt=dt)
        self._plant.reset(
            np.array([state.east]), np.array([state.north]), np.array([math.pi / 2 - state.yaw])
        )

    def drive(self, speed: float, yaw_ned: float) -> None:
        """One plant step (the plant's dt) toward ``speed`` (m/s) and NED ``yaw_ned``."""
        p = self._plant
        p.step([speed], [wrap_pi(math.pi / 2 - yaw_ned)])
        s = self.state
        s.east, s.north = float(p.x[0]), float(p.y[0])
        s.yaw = wrap_pi(math.pi / 2 - float(p.heading[0]))
        s.speed = float(p.speed[0])
        s.yaw_rate = -float(p.yaw_rate[0])
        s.accel = float(p.accel[0])

    @property
    def dt(self) -> float:
        return self._plant.dt
