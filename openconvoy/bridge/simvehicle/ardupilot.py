"""A model of ArduPilot Rover 4.7's GUIDED behaviour, as recorded in shared/sitl/.

What it reproduces (the numbers of shared/sitl/README.md, rows in brackets):

- boot: first heartbeat INITIALISING (16); "ArduPilot Ready" sets INITIAL_MODE (MANUAL)
  [3]; the RC mode switch's first reading 0.42 s later sets MODE6 = MANUAL (channel 8 at
  1800 µs) [4]; later mode requests stick [5];
- arming: "System not initialised", then the IMU checks ("Accels inconsistent", "Gyros
  inconsistent"), then, in GUIDED only, "AHRS: not using configured AHRS type" until the
  EKF uses GPS; result 4 with the reason as STATUSTEXT [1, 2];
- setpoints (``Rover/GCS_MAVLink_Rover.cpp``): ignored outside GUIDED and, in LOCAL_NED,
  before the EKF origin [24, 25]; speed |(vx, vy)| capped at WP_SPEED [14]; with the yaw
  or yaw-rate field in use, reverse iff vx ≤ −FLT_EPSILON whatever vy is [6–8, 10];
  velocity only: heading atan2(vy, vx), never reverse, so (0, 0) means north [9, 21, 22];
- GUIDED: "target not received last 3secs, stopping" 3 s after the last setpoint, then a
  controlled stop, staying in GUIDED [19]; HOLD: throttle 0, coasting [23];
- SET_MESSAGE_INTERVAL: a rate at or above SCHED_LOOP_RATE (50 Hz) is DENIED with
  "Requested rate for message ID N too fast. Increase SCHED_LOOP_RATE" [26];
- the controllers (``libraries/APM_Control/AR_AttitudeControl.cpp``,
  ``libraries/AR_Motors/AP_MotorsUGV.cpp``) with the stock rover.parm gains, driving
  ``simvehicle.motion.SitlRover``: the accel-limited speed target with its PI loop and cruise
  feed-forward gives the recorded ~0.3 s dead time and ~0.3 m/s overshoot [11–13]; the
  heading P + turn-rate PID with its acceleration and G limits, and the motors' steering
  scaling by 1/speed, give the recorded heading steps [15–17] and 0.94·r turn rates [10].

Or, with a ``VehiclePreset``, the same firmware logic drives the simulator's plant
(``simvehicle.motion.PresetMotion``) with speed and heading targets instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.motion import MotionState, PresetMotion, SitlRover, wrap_pi

FLT_EPSILON = 1.1920929e-07
SCHED_LOOP_RATE_HZ = 50.0
LOOP_DT = 1.0 / SCHED_LOOP_RATE_HZ
MODE_INITIALISING = 16
MODE_NUMBERS = {"MANUAL": 0, "HOLD": 4, "GUIDED": 15, "INITIALISING": MODE_INITIALISING}
MODE_NAMES = {v: k for k, v in MODE_NUMBERS.items()}
_SETTABLE = {0, 4, 15}
_CONTROL_TIMEOUT_S = 0.2  # AR_ATTCONTROL_TIMEOUT_MS
_RC_SWITCH_DELAY_S = 0.42  # "ArduPilot Ready" -> the RC mode switch's first reading


@dataclass(frozen=True)
class ArduPilotTiming:
    """Boot timeline, seconds after boot. ``firmware()`` is the recorded one."""

    first_heartbeat_s: float
    init_s: float  # "ArduPilot Ready": INITIAL_MODE set
    accels_ok_s: float
    gyros_ok_s: float
    gps_s: float  # GPS fix: LOCAL_POSITION_NED starts (before the origin!)
    origin_s: float  # "EKF3 IMU0 origin set": LOCAL_NED setpoints accepted
    ekf_gps_s: float  # "EKF3 IMU0 is using GPS": GUIDED armable
    rc_delay_s: float = _RC_SWITCH_DELAY_S  # "ArduPilot Ready" -> first RC mode reading

    @staticmethod
    def firmware() -> ArduPilotTiming:
        return ArduPilotTiming(0.85, 2.34, 12.5, 22.5, 10.39, 19.93, 41.95)

    @staticmethod
    def short(ready_after_s: float, init_s: float | None = None) -> ArduPilotTiming:
        """The firmware's order, compressed so that GUIDED is armable at ``ready_after_s``;
        ``init_s`` moves "ArduPilot Ready" (and the RC switch 0.42 s later) on its own."""
        f = ArduPilotTiming.firmware()
        k = ready_after_s / f.ekf_gps_s
        init = f.init_s * k if init_s is None else init_s
        return ArduPilotTiming(
            min(f.first_heartbeat_s * k, init),
            init,
            max(init, f.accels_ok_s * k),
            max(init, f.gyros_ok_s * k),
            f.gps_s * k,
            f.origin_s * k,
            max(init, ready_after_s),
            f.rc_delay_s * k if init_s is None else f.rc_delay_s,
        )


class _Pid:
    """AC_PID's update_all as Rover uses it: error filter, P, I with anti-windup."""

    def __init__(self, kp: float, ki: float, imax: float, filt_hz: float) -> None:
        self.kp, self.ki, self.imax = kp, ki, imax
        self._rc = 1.0 / (2.0 * math.pi * filt_hz)
        self.integrator = 0.0
        self.error = 0.0
        self._reset = True

    def reset(self) -> None:
        self.integrator = 0.0
        self._reset = True

    def update(self, target: float, measured: float, dt: float, limit: bool) -> float:
        err = target - measured
        if self._reset:
            self.error = err
            self._reset = False
        else:
            self.error += dt / (dt + self._rc) * (err - self.error)
        e = self.error
        if not limit or (self.integrator > 0 > e) or (self.integrator < 0 < e):
            self.integrator = max(-self.imax, min(self.imax, self.integrator + e * self.ki * dt))
        return self.kp * e + self.integrator


class RoverControl:
    """AR_AttitudeControl + AP_MotorsUGV (regular steering) with rover.parm's values.

    Outputs are servo fractions −1…1: ``throttle`` and ``steering`` after the motors'
    slew limit and speed scaling."""

    def __init__(self, state: MotionState) -> None:
        self.s = state
        self.str_ang_p = 2.0
        self.str_rate_max = math.radians(120.0)
        self.str_acc_max = math.radians(120.0)
        self.str_ff = 0.75
        self.lat_accel_max = 0.6 * 9.80665  # ATC_TURN_MAX_G
        self.accel_max = 1.0  # ATC_ACCEL_MAX (ATC_DECEL_MAX 0 = the same)
        self.cruise_speed, self.cruise_throttle = 5.0, 0.30
        self.stop_speed = 0.1
        self.slew_per_s = 1.0  # MOT_SLEWRATE 100 %/s
        self._str_pid = _Pid(0.2, 0.2, 1.0, 10.0)
        self._spd_pid = _Pid(0.1, 0.2, 1.0, 10.0)
        self.desired_speed = 0.0
        self.desired_turn_rate = 0.0
        self._t_speed = -math.inf
        self._t_turn = -math.inf
        self._t_stop = -math.inf
        self._thr_limit_low = self._thr_limit_high = False
        self.limit_steer = False
        self.limit_throttle = False
        self.throttle = 0.0  # motors' (slew-limited) output, −1…1
        self.steering = 0.0

    # --- steering
    def steer_to_heading(self, yaw: float, t: float, dt: float) -> float:
        err = wrap_pi(yaw - self.s.yaw)
        rate = self.str_ang_p * err
        cap = math.sqrt(2.0 * abs(err) * self.str_acc_max)
        return self.steer_at_rate(max(-cap, min(cap, rate)), t, dt)

    def steer_at_rate(self, rate: float, t: float, dt: float) -> float:
        if t - self._t_turn > _CONTROL_TIMEOUT_S:
            self._str_pid.reset()
            self.desired_turn_rate = self.s.yaw_rate
        self._t_turn = t
        step = self.str_acc_max * dt
        rate = max(self.desired_turn_rate - step, min(self.desired_turn_rate + step, rate))
        rate = max(-self.str_rate_max, min(self.str_rate_max, rate))
        g_cap = max(self.lat_accel_max / max(abs(self.s.speed), 1.0), math.radians(1.0))
        rate = max(-g_cap, min(g_cap, rate))
        self.desired_turn_rate = rate
        out = self._str_pid.update(rate, self.s.yaw_rate, dt, self.limit_steer)
        return out + self.str_ff * rate

    # --- throttle
    def _active(self, t: float) -> bool:
        return t - self._t_speed <= _CONTROL_TIMEOUT_S

    def accel_limited(self, desired: float, t: float, dt: float) -> float:
        if not self._active(t):
            return desired
        step = self.accel_max * dt
        return max(self.desired_speed - step, min(self.desired_speed + step, desired))

    def throttle_for_speed(self, desired: float, t: float, dt: float) -> float:
        speed = self.s.speed
        if not self._active(t):
            self._spd_pid.reset()
            self.desired_speed = speed
        self._t_speed = t
        self.desired_speed = self.accel_limited(desired, t, dt)
        base = self.desired_speed * self.cruise_throttle / self.cruise_speed
        limit = self.limit_throttle or self._thr_limit_low or self._thr_limit_high
        out = self._spd_pid.update(self.desired_speed, speed, dt, limit) + base
        self._thr_limit_low = self._thr_limit_high = False  # ATC_BRAKE 1: reverse allowed
        return out

    def throttle_to_stop(self, t: float, dt: float) -> float:
        stopped = t - self._t_stop < 0.3
        limited = self.accel_limited(0.0, t, dt)
        if limited == 0.0 and abs(self.s.speed) <= self.stop_speed:
            stopped = True
        if stopped:
            self._t_stop = t
            self._t_speed = t
            self._spd_pid.reset()
            self.desired_speed = 0.0
            return 0.0
        self._t_stop = -math.inf
        return self.throttle_for_speed(limited, t, dt)

    def drive(self, target_speed: float, t: float, dt: float) -> float:
        """Mode::calc_throttle: the speed or the stop controller."""
        target = self.accel_limited(target_speed, t, dt)
        if target == 0.0:
            return self.throttle_to_stop(t, dt)
        return self.throttle_for_speed(target, t, dt)

    # --- motors
    def output(self, armed: bool, throttle: float, steering: float, scale: bool, dt: float) -> None:
        """AP_MotorsUGV::output_regular: slew, steering scaling, limits, constraints."""
        if not armed:
            self.throttle = self.steering = 0.0
            self.limit_steer = self.limit_throttle = True
            return
        throttle = max(-1.0, min(1.0, throttle))
        step = self.slew_per_s * dt
        slewed = max(self.throttle - step, min(self.throttle + step, throttle))
        slew_limited = slewed != throttle  # slew_limit_throttle sets the limit flags too
        throttle = slewed
        self.limit_steer = False
        speed = self.s.speed
        if scale:
            if abs(speed) > 1.0:  # MOT_SPD_SCA_BASE
                steering /= abs(speed)
            else:
                self.limit_steer = True  # low speed: stop the I-term building up
            if speed < 0:
                steering = -steering
        self.limit_steer |= abs(steering) >= 1.0
        self.limit_throttle = abs(throttle) >= 1.0 or slew_limited
        self.throttle = throttle
        self.steering = max(-1.0, min(1.0, steering))


class ArduPilotRover:
    """The firmware's state machine and loops; the shell (``simvehicle``) does the I/O.

    ``motion``: ``SitlRover`` (servo outputs, the recorded firmware's test vehicle) or
    ``PresetMotion`` (targets, the simulator's plant)."""

    autopilot_id = mp.AUTOPILOT_ARDUPILOT
    loop_dt = LOOP_DT
    clock_ratio = 1.0

    def __init__(
        self,
        state: MotionState,
        timing: ArduPilotTiming,
        rc_mode_switch: bool = True,
        wp_speed_mps: float = 5.0,
        setpoint_timeout_s: float = 3.0,
        motion: SitlRover | PresetMotion | None = None,
    ) -> None:
        self.state = state
        self.timing = timing
        self.rc_mode_switch = rc_mode_switch
        self.wp_speed = wp_speed_mps
        self.setpoint_timeout_s = setpoint_timeout_s
        self.motion = motion if motion is not None else SitlRover(state)
        self.control = RoverControl(state)
        self.first_heartbeat_s = timing.first_heartbeat_s
        self.mode_number = MODE_INITIALISING
        self.heartbeat_now = False
        self.armed = False
        self.texts: list[tuple[int, str]] = []
        self._initialised = False
        self._rc_read = False
        self._announced: set[str] = set()
        # GUIDED targets
        self._have_target = False
        self._t_target = -math.inf
        self._target_speed = 0.0
        self._target_yaw = 0.0
        self._target_rate: float | None = None
        self.setpoints_received = 0
        self.setpoints_ignored = 0
        self._substeps = 2

    # --- status
    @property
    def mode(self) -> str:
        return MODE_NAMES.get(self.mode_number, f"MODE{self.mode_number}")

    def heartbeat(self, t: float) -> tuple[int, int, int]:
        """(base_mode, custom_mode, system_status) as ArduPilot Rover sends them."""
        base = 1 | (64 if self.mode_number == 0 else 0) | (8 if self.mode_number == 15 else 0)
        if self.armed:
            base |= 128
        return base, self.mode_number, (4 if self._initialised else 2)

    def origin_set(self, t: float) -> bool:
        return t >= self.timing.origin_s

    def position_flowing(self, t: float) -> bool:
        """LOCAL_POSITION_NED is sent from the GPS fix on, ~9.5 s before the origin."""
        return t >= self.timing.gps_s

    def rc_channels(self) -> list[int]:
        if not self._rc_read:
            return [0] * 8
        return [1500, 1500, 1500, 1500, 1800, 1500, 1500, 1800]

    def servo_pwm(self) -> tuple[int, int]:
        """(steering servo1, throttle servo3) in µs."""
        c = self.control
        return int(round(1500 + 500 * c.steering)), int(round(1500 + 500 * c.throttle))

    # --- commands
    def set_mode(self, number: int, by: str = "gcs") -> int:
        if number not in _SETTABLE:
            return mp.RESULT_FAILED
        if number == 15 and self.mode_number != 15:
            self._have_target = False  # GUIDED starts stopped
        self._change_mode(number)
        return mp.RESULT_ACCEPTED

    def _change_mode(self, number: int) -> None:
        if number != self.mode_number:
            self.heartbeat_now = True  # ArduPilot announces a new mode with a heartbeat
        self.mode_number = number

    def pilot_set_mode(self, name: str) -> None:
        self.set_mode(MODE_NUMBERS[name], by="pilot")
        self.texts.append((6, f"Mode changed to {name}"))

    def command(self, t: float, command: int, params: list[float]) -> int:
        if command == mp.CMD_DO_SET_MODE:
            return self.set_mode(int(params[1]))
        if command == mp.CMD_COMPONENT_ARM_DISARM:
            return self._arm(t, params[0] > 0.5, int(params[1]) == 21196)
        return mp.RESULT_UNSUPPORTED

    def interval(self, msg_id: int, hz: float) -> int:
        if hz >= SCHED_LOOP_RATE_HZ:
            self.texts.append(
                (6, f"Requested rate for message ID {msg_id} too fast. Increase SCHED_LOOP_RATE")
            )
            return mp.RESULT_DENIED
        return mp.RESULT_ACCEPTED

    def _arm(self, t: float, arm: bool, force: bool) -> int:
        if not arm:
            if self.armed:
                self.armed = False
                self.texts.append((6, "Throttle disarmed"))
            return mp.RESULT_ACCEPTED
        if self.armed:
            return mp.RESULT_ACCEPTED
        reasons = [] if force else self._arming_failures(t)
        if reasons:
            self.texts.extend((2, f"Arm: {r}") for r in reasons)
            return mp.RESULT_FAILED
        self.armed = True
        self.texts.append((6, "Throttle armed"))
        return mp.RESULT_ACCEPTED

    def _arming_failures(self, t: float) -> list[str]:
        tm = self.timing
        if not self._initialised:
            return ["System not initialised"]
        out = []
        if t < tm.accels_ok_s:
            out.append("Accels inconsistent")
        elif t < tm.gyros_ok_s:
            out.append("Gyros inconsistent")
        if self.mode_number == 15 and t < tm.ekf_gps_s:  # modes that need a position
            out.append("AHRS: not using configured AHRS type")
        return out

    # --- setpoints
    def setpoint(
        self,
        t: float,
        local: bool,
        frame: int,
        mask: int,
        vx: float,
        vy: float,
        yaw: float,
        yaw_rate: float,
    ) -> None:
        """SET_POSITION_TARGET_{LOCAL_NED,GLOBAL_INT} as GCS_MAVLink_Rover.cpp handles them."""
        if self.mode_number != 15 or (local and not self.origin_set(t)):
            self.setpoints_ignored += 1
            return
        pos_ign = mask & mp.MASK_POS == mp.MASK_POS
        vel_ign = mask & mp.MASK_VEL == mp.MASK_VEL
        acc_ign = mask & mp.MASK_ACC == mp.MASK_ACC
        yaw_ign = bool(mask & mp.MASK_YAW)
        rate_ign = bool(mask & mp.MASK_YAW_RATE)
        body = frame in (8, 9)  # MAV_FRAME_BODY_NED, BODY_OFFSET_NED
        speed, heading = 0.0, 0.0
        if not vel_ign:
            speed = min(math.sqrt(vx * vx + vy * vy), self.wp_speed)
            heading = math.atan2(vy, vx) + (self.state.yaw if body else 0.0)
        if not yaw_ign:
            heading = yaw + (self.state.yaw if body else 0.0)
        direction = (
            -1.0 if (not vel_ign and (not yaw_ign or not rate_ign) and vx <= -FLT_EPSILON) else 1.0
        )
        if not (pos_ign and acc_ign):
            self.setpoints_ignored += 1  # positions are not modelled; acceleration: invalid
            return
        if not vel_ign and yaw_ign and rate_ign:
            self._set_heading_speed(t, heading, speed)
        elif not vel_ign and yaw_ign and not rate_ign:
            self._set_rate_speed(t, yaw_rate, direction * speed)
        elif not vel_ign and not yaw_ign and rate_ign:
            self._set_heading_speed(t, heading, direction * speed)
        elif vel_ign and yaw_ign and not rate_ign:
            self._set_rate_speed(t, yaw_rate, 0.0)
        elif vel_ign and not yaw_ign and rate_ign:
            self._set_heading_speed(t, heading, 0.0)
        else:
            self.setpoints_ignored += 1
            return
        self.setpoints_received += 1

    def _set_heading_speed(self, t: float, yaw: float, speed: float) -> None:
        self._have_target, self._t_target = True, t
        self._target_yaw, self._target_speed, self._target_rate = wrap_pi(yaw), speed, None

    def _set_rate_speed(self, t: float, rate: float, speed: float) -> None:
        self._have_target, self._t_target = True, t
        self._target_speed, self._target_rate = speed, rate

    # --- the loop
    def tick(self, t: float) -> None:
        """One 50 Hz scheduler loop at vehicle time ``t``: boot events, mode, motion."""
        self._boot_events(t)
        dt = self.loop_dt
        c = self.control
        speed, yaw, rate, coast = 0.0, self.state.yaw, None, True
        throttle = steering = 0.0
        if self.mode_number == 15:
            if self._have_target and t - self._t_target > self.setpoint_timeout_s:
                self.texts.append((4, "target not received last 3secs, stopping"))
                self._have_target = False
            coast = False
            if self._have_target:
                speed = self._target_speed
                if self._target_rate is None:
                    yaw = self._target_yaw
                    steering = c.steer_to_heading(yaw, t, dt)
                else:
                    rate = self._target_rate
                    steering = c.steer_at_rate(rate, t, dt)
                throttle = c.drive(speed, t, dt)
            else:
                throttle = c.throttle_to_stop(t, dt)  # Mode::stop_vehicle, steering 0
        c.output(self.armed, throttle, steering, scale=not coast, dt=dt)
        if isinstance(self.motion, PresetMotion):
            self._drive_preset(speed if (self.armed and not coast) else 0.0, yaw, rate)
            return
        # The servos carry whole microseconds: the vehicle sees the quantised outputs.
        steer_pwm, thr_pwm = self.servo_pwm()
        throttle, steering = (thr_pwm - 1500) / 500.0, (steer_pwm - 1500) / 500.0
        h = dt / self._substeps
        for _ in range(self._substeps):
            self.motion.step(throttle, steering, h)

    def _drive_preset(self, speed: float, yaw: float, rate: float | None) -> None:
        assert isinstance(self.motion, PresetMotion)  # called only for preset motion
        if rate is not None:
            yaw = self.state.yaw + rate * 0.5  # aim a short way ahead
        n = max(1, int(round(self.loop_dt / self.motion.dt)))
        for _ in range(n):
            self.motion.drive(speed, yaw)

    def _boot_events(self, t: float) -> None:
        tm = self.timing
        if not self._initialised and t >= tm.init_s:
            self._initialised = True
            self._change_mode(0)  # INITIAL_MODE = MANUAL, overriding any earlier request
            self.texts.append((6, "ArduPilot Ready"))
        if (
            self.rc_mode_switch
            and not self._rc_read
            and self._initialised
            and t >= tm.init_s + tm.rc_delay_s
        ):
            self._rc_read = True
            self._change_mode(0)  # channel 8 at 1800 us -> MODE6 = MANUAL
        for key, at, text in (
            ("origin", tm.origin_s, "EKF3 IMU0 origin set"),
            ("gps", tm.ekf_gps_s, "EKF3 IMU0 is using GPS"),
        ):
            if key not in self._announced and t >= at and self._initialised:
                self._announced.add(key)
                self.texts.append((6, text))
