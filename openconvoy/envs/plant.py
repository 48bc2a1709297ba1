"""The plant: kinematic bicycles with their autopilot inner loops, vectorized over vehicles.

Each vehicle takes a speed setpoint (m/s) and an absolute heading setpoint (rad, ENU).
After the preset's delays:

- speed (``speed_loop = "lag"``) follows with a first-order lag clipped by the acceleration
  limits; or (``"pi"``) the setpoint is ramped at the acceleration limits and tracked by
  the autopilot's PI speed controller with feed-forward, whose drive command the vehicle's
  speed follows with a first-order lag (and optional quadratic drag) (shared/sitl/README.md §3: dead time, overshoot, no
  undershoot on stops). A vehicle at rest stays there while its drive is below the
  preset's static friction (``breakaway_mps``).
- heading turns at ``err / heading_lag_s``, clipped to the turn-rate limit, slewed at the
  yaw acceleration limit, and capped by the bicycle's curvature and the lateral
  acceleration limit at the current speed (no turning on the spot).

The reference point moves along the heading. Matches shared/AUTOPILOTS.md's Rover response;
the ``pi`` presets are fitted to real firmware (``fit-plant``).
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

PI_MAX_DT_S = 0.02
"""The ``pi`` speed loop runs in substeps of at most this (s), the autopilots' 50 Hz loop:
at 20 Hz Euler steps its stop logic would miss the zero crossing (-0.40 m/s undershoot
from 5 m/s instead of the firmware's -0.10)."""


def pi_delay_split(delay_s: float, dt: float) -> tuple[int, int, float, int, float]:
    """A ``pi`` loop's speed delay, not rounded to ticks: ``(k, n1, h1, n2, h2)``. During
    a tick the setpoint sent k + 1 ticks ago acts for the first ``n1`` substeps of ``h1``
    seconds, then the one sent k ticks ago for ``n2`` substeps of ``h2`` (substeps of at
    most ``PI_MAX_DT_S``; ``n1`` = 0 when the delay is whole ticks)."""
    k = int(math.floor(delay_s / dt + 1e-9))
    frac = max(0.0, delay_s - k * dt)
    if frac < 1e-9 or frac > dt - 1e-9:
        k, frac = (k + 1, 0.0) if frac > dt - 1e-9 else (k, 0.0)
    n1 = math.ceil(frac / PI_MAX_DT_S - 1e-9) if frac > 0.0 else 0
    n2 = max(1, math.ceil((dt - frac) / PI_MAX_DT_S - 1e-9))
    return k, n1, (frac / n1 if n1 else 0.0), n2, (dt - frac) / n2


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
        self._columns(dt)
        self.x = np.zeros(n)
        self.y = np.zeros(n)
        self.heading = np.zeros(n)
        self.speed = np.zeros(n)
        self.accel = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        # Inner-loop state: the ramped speed setpoint and the PI integrator (``pi``), and the
        # heading loop's slewed desired yaw rate.
        self._ramp = np.zeros(n)
        self._integ = np.zeros(n)
        self._rate_des = np.zeros(n)
        self._queue_v = np.zeros((self._depth, n))
        self._queue_h = np.zeros((self._depth, n))
        self._head = 0
        self._idx = np.arange(n)
        self._vectorized = n > SCALAR_MAX_VEHICLES if vectorized is None else vectorized
        self._scalar_copies()

    def _columns(self, dt: float) -> None:
        """The presets' parameters as arrays (one entry per vehicle), delays in steps."""
        n = len(self.presets)
        col = lambda attr: np.array([getattr(p, attr) for p in self.presets], dtype=float)  # noqa: E731
        self._tau_v = np.maximum(col("speed_lag_s"), 1e-6)
        self._tau_h = np.maximum(col("heading_lag_s"), 1e-6)
        self._acc = col("accel_max_mps2")
        self._dec = col("decel_max_mps2")
        self._rate = col("turn_rate_max_radps")
        self._vmax = col("max_speed_mps")
        self._kappa = np.tan(col("max_steer_rad")) / col("wheelbase_m")
        # The speed is the one reported: the velocity projected on the believed heading,
        # which is off by the heading bias; the vehicle moves 1 / cos(bias) as fast.
        self._move = 1.0 / np.cos(col("heading_bias_rad"))
        self._pi = np.array([p.speed_loop == "pi" for p in self.presets], dtype=bool)
        self._any_pi = bool(self._pi.any())
        self._pi_sub = max(1, math.ceil(dt / PI_MAX_DT_S - 1e-9))
        self._kp = col("speed_kp")
        self._ki = col("speed_ki")
        self._ff = col("speed_ff")
        self._tau_d = np.maximum(col("drive_lag_s"), 1e-6)
        self._drag = col("drive_drag_per_mps")
        self._stop = col("stop_speed_mps")
        self._brk = col("breakaway_mps")
        self._kin = col("kinetic_friction_mps")
        self._yaw_acc = col("yaw_accel_max_radps2")
        self._alat = col("lateral_accel_max_mps2")
        steps = lambda delays: np.array([int(round(d / dt)) for d in delays], dtype=int)  # noqa: E731
        self._hdelay_steps = steps(p.heading_delay for p in self.presets)
        # The pi loop's speed delay is not whole ticks (``pi_delay_split``); the lag
        # loop's is rounded to ticks.
        whole = (0, 0.0, self._pi_sub, dt / self._pi_sub)
        split = [
            pi_delay_split(p.actuation_delay_s, dt)
            if p.speed_loop == "pi"
            else (int(round(p.actuation_delay_s / dt)), *whole)
            for p in self.presets
        ]
        self._delay_steps = np.array([x[0] for x in split], dtype=int)
        self._sub_n1 = np.array([x[1] for x in split], dtype=int)
        self._sub_h1 = np.array([x[2] for x in split], dtype=float)
        self._sub_n2 = np.array([x[3] for x in split], dtype=int)
        self._sub_h2 = np.array([x[4] for x in split], dtype=float)
        self._depth = (
            int(max(self._delay_steps.max() + 1, self._hdelay_steps.max())) + 1 if n else 1
        )

    def _scalar_copies(self) -> None:
        """The scalar step's copies of the parameters and of the setpoint queue."""
        n = len(self.presets)
        self._params = list(
            zip(
                self._tau_v.tolist(),
                self._tau_h.tolist(),
                self._acc.tolist(),
                self._dec.tolist(),
                self._rate.tolist(),
                self._vmax.tolist(),
                self._kappa.tolist(),
                self._delay_steps.tolist(),
                self._hdelay_steps.tolist(),
                self._pi.tolist(),
                list(
                    zip(
                        self._sub_n1.tolist(),
                        self._sub_h1.tolist(),
                        self._sub_n2.tolist(),
                        self._sub_h2.tolist(),
                    )
                ),
                self._brk.tolist(),
                self._yaw_acc.tolist(),
                self._alat.tolist(),
                (np.isinf(self._yaw_acc) & np.isinf(self._alat)).tolist(),
            )
        )
        self._pi_params = list(
            zip(
                self._kp.tolist(),
                self._ki.tolist(),
                self._ff.tolist(),
                self._tau_d.tolist(),
                self._stop.tolist(),
                self._drag.tolist(),
                self._kin.tolist(),
            )
        )
        self._qv: list[list[float]] = [[0.0] * n for _ in range(self._depth)]
        self._qh: list[list[float]] = [[0.0] * n for _ in range(self._depth)]
        # The scalar step keeps the inner-loop state as lists (no conversions per step).
        self._ramp_l, self._integ_l, self._rate_des_l = [0.0] * n, [0.0] * n, [0.0] * n
        self._move_l = self._move.tolist()

    def __len__(self) -> int:
        return len(self.presets)

    def reset(
        self,
        x: np.ndarray,
        y: np.ndarray,
        heading: np.ndarray,
        speed: np.ndarray | None = None,
    ) -> None:
        """Place the vehicles; pending setpoints hold the initial speed and heading, and the
        inner loops start in steady state at that speed."""
        n = len(self)
        self.x = np.asarray(x, dtype=float).copy()
        self.y = np.asarray(y, dtype=float).copy()
        self.heading = np.asarray(heading, dtype=float).copy()
        self.speed = np.zeros(n) if speed is None else np.asarray(speed, dtype=float).copy()
        self.accel = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        self._ramp = self.speed.copy()
        # Steady state at the setpoint: the drive holds the speed against the drag
        # (ff * v + integrator = v + drag * v|v|). Without an integrator that offset stays.
        v = self.speed
        self._integ = np.where(self._pi, v + self._drag * v * np.abs(v) - self._ff * v, 0.0)
        self._rate_des = np.zeros(n)
        self._ramp_l, self._integ_l = self._ramp.tolist(), self._integ.tolist()
        self._rate_des_l = [0.0] * n
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
        slot_v = (self._head - self._delay_steps) % self._depth
        slot_h = (self._head - self._hdelay_steps) % self._depth
        v_cmd = np.clip(self._queue_v[slot_v, self._idx], -self._vmax, self._vmax)
        v_before = np.clip(
            self._queue_v[(slot_v - 1) % self._depth, self._idx], -self._vmax, self._vmax
        )
        h_cmd = self._queue_h[slot_h, self._idx]
        self._head = (self._head + 1) % self._depth

        v = self.speed
        # Speed, lag: first-order lag, clipped to the acceleration limits.
        dv = np.clip((v_cmd - v) / self._tau_v, -self._dec, self._acc) * dt
        # Never overshoot the setpoint within one step.
        dv = np.where(np.abs(dv) > np.abs(v_cmd - v), v_cmd - v, dv)
        if self._brk.any():  # static friction holds a vehicle at rest
            dv = np.where((v == 0.0) & (np.abs(v_cmd) < self._brk), 0.0, dv)
        if self._any_pi:
            dv = np.where(self._pi, self._pi_dv(v_cmd, v_before), dv)
        v_new = v + dv

        # Heading: lag towards the setpoint, clipped by turn rate, slewed by the yaw
        # acceleration limit, capped by curvature and lateral acceleration at speed.
        err = (h_cmd - self.heading + math.pi) % (2.0 * math.pi) - math.pi
        v_mid = 0.5 * (v + v_new)
        wanted = np.clip(err / np.maximum(self._tau_h, dt), -self._rate, self._rate)
        slew = self._yaw_acc * dt
        self._rate_des = np.clip(wanted, self._rate_des - slew, self._rate_des + slew)
        speed_mid = np.abs(v_mid)
        cap = np.minimum(speed_mid * self._kappa, self._alat / np.maximum(speed_mid, 1e-9))
        rate = np.clip(self._rate_des, -cap, cap)
        h_mid = self.heading + 0.5 * rate * dt

        self.x = self.x + self._move * v_mid * np.cos(h_mid) * dt
        self.y = self.y + self._move * v_mid * np.sin(h_mid) * dt
        self.heading = (self.heading + rate * dt + math.pi) % (2.0 * math.pi) - math.pi
        self.accel = dv / dt
        self.yaw_rate = rate
        self.speed = v_new

    def _pi_dv(self, v_cmd: np.ndarray, v_before: np.ndarray) -> np.ndarray:
        """The ``pi`` speed loop's speed change over one step (numpy; updates its state):
        ``v_before`` (the setpoint a tick older) acts for the first substeps
        (``pi_delay_split``)."""
        v0 = v = self.speed
        r, integ = self._ramp, self._integ
        v_now = v_cmd
        n1, n2 = self._sub_n1, self._sub_n2
        for j in range(int((n1 + n2).max())):
            first = j < n1
            active = j < n1 + n2
            h = np.where(first, self._sub_h1, np.where(active, self._sub_h2, 0.0))
            v_cmd = np.where(first, v_before, v_now)
            r_old, integ_old, v_old = r, integ, v
            # Ramp the setpoint: the accel limit speeding up, the decel limit slowing down.
            lim = np.where(np.abs(v_cmd) > np.abs(r), self._acc, self._dec) * h
            r = r + np.clip(v_cmd - r, -lim, lim)
            err = r - v
            stopped = (r == 0.0) & (np.abs(v) <= self._stop)
            integ = np.where(stopped, 0.0, integ + self._ki * err * h)
            drive = np.where(stopped, 0.0, self._ff * r + self._kp * err + integ)
            kf = self._kin * np.where(v == 0.0, np.sign(drive), np.sign(v))
            dv = (drive - v - self._drag * v * np.abs(v) - kf) / self._tau_d * h
            # Friction: at rest below breakaway nothing moves; slowing down stops at zero,
            # and a stopped vehicle (drive cut) comes to rest rather than coasting on.
            held = np.abs(drive) < np.maximum(self._brk, self._kin)
            stuck = held & ((v == 0.0) | ((v + dv) * v < 0.0) | stopped)
            v = np.where(stuck, 0.0, v + dv)
            r, integ, v = (
                np.where(active, a, b) for a, b in ((r, r_old), (integ, integ_old), (v, v_old))
            )
        self._ramp = np.where(self._pi, r, self._ramp)
        self._integ = np.where(self._pi, integ, self._integ)
        return v - v0

    def _step_scalar(self, cmd_speed: Sequence[float], cmd_heading: Sequence[float]) -> None:
        """``step`` on Python floats, the same equations vehicle by vehicle."""
        dt, depth, head = self.dt, self._depth, self._head
        self._qv[head] = [float(v) for v in cmd_speed]
        self._qh[head] = [float(h) for h in cmd_heading]
        self._head = (head + 1) % depth
        two_pi, pi = 2.0 * math.pi, math.pi
        xs, ys, hs, vs = (a.tolist() for a in (self.x, self.y, self.heading, self.speed))
        ramp, integ, rate_des = self._ramp_l, self._integ_l, self._rate_des_l
        acc_out, rate_out = [0.0] * len(vs), [0.0] * len(vs)
        move = self._move_l
        for i, (
            tau_v,
            tau_h,
            acc,
            dec,
            rate_max,
            vmax,
            kappa,
            delay,
            hdelay,
            is_pi,
            substeps,
            brk,
            yaw_acc,
            alat,
            plain_heading,
        ) in enumerate(self._params):
            v_cmd = min(max(self._qv[(head - delay) % depth][i], -vmax), vmax)
            v = vs[i]
            if is_pi:
                v_before = min(max(self._qv[(head - delay - 1) % depth][i], -vmax), vmax)
                vs_, ramp[i], integ[i] = pi_speed_loop(
                    v_cmd, v, ramp[i], integ[i], self._pi_params[i], acc, dec, brk, v_before,
                    substeps,
                )  # fmt: skip
                dv = vs_ - v
            else:
                dv = lag_speed_change(v_cmd, v, tau_v, acc, dec, brk, dt)
            v_new = v + dv
            err_h = (self._qh[(head - hdelay) % depth][i] - hs[i] + pi) % two_pi - pi
            v_mid = 0.5 * (v + v_new)
            if plain_heading:  # no slew, no lateral limit: one clip (the same numbers)
                cap = min(rate_max, abs(v_mid) * kappa)
                rate = min(max(err_h / max(tau_h, dt), -cap), cap)
            else:
                rate, rate_des[i] = slewed_yaw_rate(
                    err_h, v_mid, rate_des[i], tau_h, rate_max, kappa, yaw_acc, alat, dt
                )
            h_mid = hs[i] + 0.5 * rate * dt
            xs[i] += move[i] * v_mid * math.cos(h_mid) * dt
            ys[i] += move[i] * v_mid * math.sin(h_mid) * dt
            hs[i] = (hs[i] + rate * dt + pi) % two_pi - pi
            vs[i] = v_new
            acc_out[i] = dv / dt
            rate_out[i] = rate
        self.x, self.y, self.heading = np.array(xs), np.array(ys), np.array(hs)
        self.speed, self.accel, self.yaw_rate = np.array(vs), np.array(acc_out), np.array(rate_out)

    def inner_state(self) -> dict[str, np.ndarray]:
        """The inner loops' state: ``ramp`` (the ramped speed setpoint, m/s) and ``integ``
        (the PI integrator, m/s) of ``pi`` vehicles; for tests and inspection."""
        if self._vectorized:
            return {"ramp": self._ramp.copy(), "integ": self._integ.copy()}
        return {"ramp": np.array(self._ramp_l), "integ": np.array(self._integ_l)}

    def state(self, i: int, t: float) -> VehicleState:
        """Vehicle ``i``'s state at time ``t`` (its id is its index)."""
        p = self.presets[i]
        return VehicleState(
            vehicle_id=i,
            t=t,
            x=float(self.x[i]),
            y=float(self.y[i]),
            speed=float(self.speed[i]),
            heading=float(self.heading[i]),
            accel=float(self.accel[i]),
            yaw_rate=float(self.yaw_rate[i]),
            length=p.length_m,
            width=p.width_m,
        )


def lag_speed_change(
    v_cmd: float, v: float, tau_v: float, acc: float, dec: float, brk: float, dt: float
) -> float:
    """The ``lag`` speed loop's speed change (m/s) over one step ``dt`` (s) for one vehicle
    on floats: towards ``v_cmd`` with time constant ``tau_v`` (s), clipped at ``acc`` and
    ``dec`` (m/s²), static friction ``brk`` (m/s) holding it at rest. The batched plant
    calls this function compiled (``envs.vector.jit.rules``)."""
    dv = min(max((v_cmd - v) / tau_v, -dec), acc) * dt
    if abs(dv) > abs(v_cmd - v):  # never overshoot the setpoint within one step
        dv = v_cmd - v
    if v == 0.0 and abs(v_cmd) < brk:
        dv = 0.0
    return dv


def pi_speed_loop(
    v_cmd: float,
    v: float,
    r: float,
    acc_i: float,
    pi_params: tuple[float, float, float, float, float, float, float],
    acc: float,
    dec: float,
    brk: float,
    v_before: float,
    substeps: tuple[int, float, int, float],
) -> tuple[float, float, float]:
    """One step of the ``pi`` speed loop for one vehicle on floats (``_pi_dv``'s
    equations): the new speed, ramped setpoint and integrator (m/s); ``v_before`` acts for
    the first ``n1`` substeps of ``h1`` s, ``v_cmd`` for the next ``n2`` of ``h2``
    (``substeps``, from ``pi_delay_split``); ``pi_params`` (kp, ki, ff, tau_d, stop,
    drag, kinetic friction). The batched plant calls this function compiled
    (``envs.vector.jit.rules``)."""
    kp, ki, ff, tau_d, stop, drag, kin = pi_params
    vs_ = v
    v_now = v_cmd
    n1, h1, n2, h2 = substeps
    for j in range(n1 + n2):
        v_cmd, h_sub = (v_before, h1) if j < n1 else (v_now, h2)
        lim = (acc if abs(v_cmd) > abs(r) else dec) * h_sub
        r += min(max(v_cmd - r, -lim), lim)
        err = r - vs_
        stopped = r == 0.0 and abs(vs_) <= stop
        if stopped:
            acc_i = drive = 0.0
        else:
            acc_i += ki * err * h_sub
            drive = ff * r + kp * err + acc_i
        vs_ = friction_speed(vs_, drive, drag, tau_d, brk, kin, stopped, h_sub)
    return vs_, r, acc_i


def friction_speed(
    v: float,
    drive: float,
    drag: float,
    tau_d: float,
    brk: float,
    kin: float,
    stopped: bool,
    h: float,
) -> float:
    """The ``pi`` loop's vehicle speed (m/s) after a substep ``h`` (s) for one vehicle on
    floats: it follows the ``drive`` (m/s) with lag ``tau_d`` (s) against quadratic
    ``drag``, static friction ``brk`` and kinetic friction ``kin`` (m/s of drive): PX4 SIH's
    Ackermann rover (PX4-Autopilot ``src/modules/simulation/simulator_sih/sih.cpp``,
    ``generate_rover_ackermann_dynamics``: 400 N · throttle against μ 0.5 static below
    0.01 m/s, 0.4 up to 0.05 m/s and 0.3 rolling above, on 20 kg; with PX4's feed-forward
    throttle, setpoint / 3.2, that is 0.78 and 0.47 m/s of drive;
    ``bridge.simvehicle.motion.SihRover``). A vehicle at rest stays there while the drive
    is below both; moving, kinetic friction opposes the motion; slowing down with the
    drive below them it stops at zero (stick-slip when ``kin < brk``). With ``kin`` 0
    the numbers are those of static friction alone, bit for bit. The batched plant calls
    this function compiled (``envs.vector.jit.rules``)."""
    if v != 0.0:
        kf = kin if v > 0.0 else -kin
    else:
        kf = kin if drive > 0.0 else (-kin if drive < 0.0 else 0.0)
    d = (drive - v - drag * v * abs(v) - kf) / tau_d * h
    if abs(drive) < max(brk, kin) and (v == 0.0 or (v + d) * v < 0.0 or stopped):
        return 0.0  # at rest it stays; slowing down it stops at zero
    return v + d


def slewed_yaw_rate(
    err_h: float,
    v_mid: float,
    rate_des: float,
    tau_h: float,
    rate_max: float,
    kappa: float,
    yaw_acc: float,
    alat: float,
    dt: float,
) -> tuple[float, float]:
    """The heading loop's yaw rate (rad/s) for one vehicle on floats, slewed and capped by
    curvature and lateral acceleration: ``(rate, new desired rate)``. The batched plant
    calls this function compiled (``envs.vector.jit.rules``)."""
    wanted = min(max(err_h / max(tau_h, dt), -rate_max), rate_max)
    slew = yaw_acc * dt
    rd = min(max(wanted, rate_des - slew), rate_des + slew)
    speed_mid = abs(v_mid)
    cap = min(speed_mid * kappa, alat / max(speed_mid, 1e-9))
    return min(max(rd, -cap), cap), rd
