"""A model of PX4's rover offboard behaviour, as recorded in shared/sitl-px4/.

PX4 main 752ecd3d1b, SIH Ackermann rover (airframe 10045), airframe defaults; rows of
shared/sitl-px4/README.md's conformance table in brackets:

- boot in AUTO.LOITER (Hold) [1]; arming refused with result 1 and "Arming denied:
  Resolve system health failures first" until ~2.3 s after the first heartbeat, and in
  OFFBOARD without a setpoint stream [2, 4];
- DO_SET_MODE OFFBOARD accepted while disarmed even with no setpoint ever (heartbeat
  base_mode 1, status 0); while armed it needs the stream, else result 1 with "Switching to
  Offboard is currently not available" [3, 5, 6];
- velocity setpoints (frames 1, 5, 6; BODY_NED re-rotated by the current yaw every
  message): bearing atan2(vy, vx) of the signed components, speed |(vx, vy)|, the yaw field
  ignored, never reverse [7–9, 20–22]; LOCAL_OFFSET_NED rejected with "...coordinate frame 7
  unsupported" [10];
- the offboard signal is lost when no setpoint came for COM_OF_LOSS_T (1.0 s): "Failsafe
  activated", POSCTL (COM_OBL_RC_ACT 0: a straight brake) or AUTO.LOITER (5: back to the
  hold point), armed throughout; when setpoints resume it is OFFBOARD again by itself
  [16–19]; Hold requested while driving also returns to its engage point [23];
- the speed loop is feed-forward only (throttle = setpoint / RO_MAX_THR_SPEED 3.2, the
  setpoint ramped at RO_ACCEL_LIM 3 m/s², capped at RO_SPEED_LIM 3) on ``SihRover``, which
  gives the dead zone from rest and the direction-dependent speeds [11–13]; the yaw loop
  is RO_YAW_P 5 into a yaw rate limited by the steering lock and a lateral acceleration
  [14, 15];
- SIH's clock runs at 0.990 of real time [24] (the firmware timing only);
- the EKF heading can be off the true one by a few degrees for a run (README §4: +0.7 to
  +5.8° at the end of each heading-step leg; the convoy run sitl-px4/convoy/r2's leader
  logged a heading drifting to -11° while its track stayed on the road):
  ``MotionState.yaw_bias``, drawn per vehicle and run (``SimVehicleConfig``). The yaw loop
  holds the estimated yaw on the bearing, so the rover really drives that much off it;
  ATTITUDE and the headings report the estimate, the velocity stays true.
- optionally (``hold_drift_mps``), Hold is not a parking brake: the position estimate
  drifts at rest, and Hold drives back to the hold point *as estimated*, so once the drift
  passes the acceptance radius the rover moves by itself, around its hold point as the
  drift turns. Observed on the firmware (shared/AUTOPILOTS.md, issue 22 "PX4 HOLD"): with
  its estimate drifting ~0.5 m at rest, PX4 drove loops around the hold point at up to
  2.2 m/s in 2 of 14 held vehicles, once 8.8 s after the deploy exited. The rover's
  Loiter is a position setpoint at the engage point, driven to whenever the estimated
  distance exceeds the acceptance radius (``HOLD_RADIUS_M``). The drift is modelled as a
  vector growing at ``hold_drift_mps`` up to ``HOLD_DRIFT_MAX_M`` and turning at
  ``HOLD_DRIFT_TURN_RADPS``; the telemetry keeps reporting the true motion (the EKF's
  velocity follows the wheels, its position the drift).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.motion import MotionState, PresetMotion, SihRover, wrap_pi

LOOP_DT = 0.02
COM_OF_LOSS_T = 1.0
_LOSS_DETECT_S = 0.03  # the failsafe fires 1.02-1.13 s after the last setpoint
RO_MAX_THR_SPEED = 3.2
RO_SPEED_LIM = 3.0
RO_ACCEL_LIM = 3.0
RO_YAW_P = 5.0
RO_YAW_RATE_LIM = math.radians(180.0)
TURN_RATE_AT_1MPS = math.radians(103.0)  # peak yaw rate ~ 103 °/s · sqrt(v): 101-105 at 1 m/s,
# 141-148 at 2 m/s in the recordings
YAW_ACCEL_LIM = math.radians(250.0)  # rad/s²: slew of the yaw-rate setpoint
BRAKE_FRACTION = 0.8  # of YAW_ACCEL_LIM planned for slowing the turn before the bearing
SPEED_DELAY_S = 0.45  # setpoint to throttle: the recorded 0.3-0.95 s before motion
STEER_LAG_S = 0.1
HOLD_RADIUS_M = 0.8
HOLD_SPEED = 1.5  # m/s: the return to the hold point
HOLD_GAIN = 1.0  # 1/s: return speed per metre beyond HOLD_RADIUS_M
HOLD_MIN_SPEED = 1.0  # m/s: enough to break away from rest (SIH's dead zone)
HOLD_DRIFT_MAX_M = 1.5  # m: the largest estimate drift modelled
HOLD_DRIFT_TURN_RADPS = 0.5  # rad/s: how fast the drift's direction turns
_ARMING_DENIED = "Arming denied: Resolve system health failures first"
_OFFBOARD_UNAVAILABLE = "Switching to Offboard is currently not available"
# (main, sub) -> name, as mavproto
MODES = dict(mp.PX4_MODES)
BASE_MODE = {"LOITER": 29, "OFFBOARD": 17, "POSCTL": 81, "MANUAL": 65}


@dataclass(frozen=True)
class Px4Timing:
    """Seconds after process start. ``firmware()`` is the recorded SIH timeline."""

    first_heartbeat_s: float
    armable_s: float
    clock_ratio: float = 1.0

    @staticmethod
    def firmware() -> Px4Timing:
        return Px4Timing(1.35, 3.6, 0.990)

    @staticmethod
    def short(ready_after_s: float) -> Px4Timing:
        return Px4Timing(0.0, ready_after_s, 1.0)


class Px4Rover:
    """PX4's commander/offboard logic and rover loops; ``simvehicle`` does the I/O."""

    autopilot_id = mp.AUTOPILOT_PX4
    loop_dt = LOOP_DT
    heartbeat_now = False  # PX4 shows a mode change at its next (1 Hz) heartbeat

    def __init__(
        self,
        state: MotionState,
        timing: Px4Timing,
        lat_deg: float,
        lon_deg: float,
        obl_rc_act: int = 0,
        motion: SihRover | PresetMotion | None = None,
        hold_drift_mps: float = 0.0,
    ) -> None:
        self.state = state
        self.hold_drift_mps = hold_drift_mps
        self._drift = (0.0, 0.0)  # (radius m, direction rad) of the estimate's drift
        self.timing = timing
        self.clock_ratio = timing.clock_ratio
        self.first_heartbeat_s = timing.first_heartbeat_s
        self.motion = motion if motion is not None else SihRover(state, lat_deg, lon_deg)
        self.params = {"COM_OBL_RC_ACT": float(obl_rc_act), "COM_OF_LOSS_T": COM_OF_LOSS_T}
        self.user_mode = "LOITER"
        self.failsafe = False
        self.armed = False
        self.texts: list[tuple[int, str]] = []
        self._t_sp = -math.inf
        self._bearing = 0.0
        self._speed = 0.0
        self._ever_sp = False
        self._hold_point: tuple[float, float] | None = (state.north, state.east)
        self._fs_mode = "POSCTL"
        self._speed_queue: deque[float] = deque([0.0] * max(1, int(round(SPEED_DELAY_S / LOOP_DT))))
        self._speed_ramped = 0.0
        self._steer = 0.0
        self._rate_sp = 0.0
        self._hold_yaw: float | None = None
        self.setpoints_received = 0
        self.setpoints_ignored = 0
        self._substeps = 2
        self._beats = 0

    # --- status
    @property
    def mode(self) -> str:
        if self.failsafe:
            return self._fs_mode
        return self.user_mode

    def signal(self, t: float) -> bool:
        return t - self._t_sp <= self.params["COM_OF_LOSS_T"] + _LOSS_DETECT_S

    def heartbeat(self, t: float) -> tuple[int, int, int]:
        mode = self.mode
        main, sub = mp.PX4_MODE_NUMBERS[mode]
        base = BASE_MODE[mode]
        if mode == "OFFBOARD" and not self.signal(t):
            base = 1
        if self.armed:
            base |= 128
        if self._beats == 0 or (mode == "OFFBOARD" and not self.armed and not self.signal(t)):
            status = 0
        elif self.failsafe:
            status = 5
        else:
            status = 4 if self.armed else 3
        self._beats += 1
        return base, mp.px4_custom_mode(main, sub), status

    def origin_set(self, t: float) -> bool:
        return True

    def position_flowing(self, t: float) -> bool:
        return True

    def rc_channels(self) -> list[int]:
        return [0] * 8

    def servo_pwm(self) -> tuple[int, int]:
        return int(round(1500 + 500 * self._steer)), int(round(1500 + 500 * self._throttle_out))

    _throttle_out = 0.0

    # --- commands
    def pilot_set_mode(self, name: str) -> None:
        self._enter(name)

    def _enter(self, name: str) -> None:
        self.failsafe = False
        if name == "LOITER":
            self._hold_point = (self.state.north, self.state.east)
            self._hold_yaw = None
            self._drift = (0.0, 0.0)
        self.user_mode = name

    def command(self, t: float, command: int, params: list[float]) -> int:
        if command == mp.CMD_DO_SET_MODE:
            name = MODES.get((int(params[1]), int(params[2])))
            if name is None:
                return mp.RESULT_DENIED
            if name == "OFFBOARD" and self.armed and not self.signal(t):
                self.texts.append((2, _OFFBOARD_UNAVAILABLE))
                return mp.RESULT_TEMPORARILY_REJECTED
            self._enter(name)
            return mp.RESULT_ACCEPTED
        if command == mp.CMD_COMPONENT_ARM_DISARM:
            if params[0] <= 0.5:
                if self.armed:
                    self.armed = False
                    self.failsafe = False  # back to the requested mode, e.g. OFFBOARD
                    self.texts.append((6, "Disarmed by external command"))
                return mp.RESULT_ACCEPTED
            if self.armed:
                return mp.RESULT_ACCEPTED
            if t < self.timing.armable_s or (self.mode == "OFFBOARD" and not self.signal(t)):
                self.texts.append((2, _ARMING_DENIED))
                return mp.RESULT_TEMPORARILY_REJECTED
            self.armed = True
            self.texts.append((6, "Armed by external command"))
            return mp.RESULT_ACCEPTED
        return mp.RESULT_UNSUPPORTED

    def interval(self, msg_id: int, hz: float) -> int:
        return mp.RESULT_ACCEPTED

    def param_set(self, name: str, value: float) -> float | None:
        if name in self.params:
            self.params[name] = float(value)
            return self.params[name]
        return None

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
        if local and frame == 7:
            self.texts.append((2, "SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported"))
            self.setpoints_ignored += 1
            return
        self._t_sp = t
        self._ever_sp = True
        if mask & mp.MASK_VEL == mp.MASK_VEL:
            self.setpoints_ignored += 1  # positions are not modelled
            return
        if frame == 8:  # BODY_NED: rotated by the current (estimated) yaw, every message
            yaw_now = self.state.estimated_yaw
            c, s = math.cos(yaw_now), math.sin(yaw_now)
            vx, vy = c * vx - s * vy, s * vx + c * vy
        self._bearing = math.atan2(vy, vx)  # signed zeros: (+0, -0) -> pi, south
        self._speed = math.hypot(vx, vy)
        self.setpoints_received += 1

    # --- the loop
    def tick(self, t: float) -> None:
        if self.armed and self.user_mode == "OFFBOARD" and not self.failsafe and not self.signal(t):
            self.failsafe = True
            self._fs_mode = "LOITER" if int(self.params["COM_OBL_RC_ACT"]) == 5 else "POSCTL"
            if self._fs_mode == "LOITER":
                self._hold_point = (self.state.north, self.state.east)
            self._hold_yaw = None
            self.texts.append((2, "Failsafe activated"))
        elif self.failsafe and self.signal(t) and self.user_mode == "OFFBOARD":
            self.failsafe = False
        if self.hold_drift_mps > 0 and self.armed and self.mode == "LOITER":
            r, direction = self._drift
            r = min(HOLD_DRIFT_MAX_M, r + self.hold_drift_mps * self.loop_dt)
            self._drift = (r, direction + HOLD_DRIFT_TURN_RADPS * self.loop_dt)
        speed, yaw = self._targets()
        if isinstance(self.motion, PresetMotion):
            n = max(1, int(round(self.loop_dt / self.motion.dt)))
            for _ in range(n):
                self.motion.drive(speed, yaw)
            return
        dt = self.loop_dt
        # The delay is the offboard path's (its setpoints queue up); Hold/POSCTL act at once.
        self._speed_queue.append(min(self._speed, RO_SPEED_LIM) if self.armed else 0.0)
        delayed = self._speed_queue.popleft()
        if self.mode != "OFFBOARD" or not self.armed:
            delayed = speed
        step = RO_ACCEL_LIM * dt
        self._speed_ramped = max(self._speed_ramped - step, min(self._speed_ramped + step, delayed))
        throttle = self._speed_ramped / RO_MAX_THR_SPEED if self.armed else 0.0
        steer = self._steering_for(yaw) if self.armed else 0.0
        self._steer += (steer - self._steer) * min(1.0, dt / STEER_LAG_S)
        self._throttle_out = throttle
        h = dt / self._substeps
        for _ in range(self._substeps):
            self.motion.step(throttle, self._steer, h)

    def _steering_for(self, yaw: float) -> float:
        s = self.state
        err = wrap_pi(yaw - s.estimated_yaw)  # the EKF's yaw is what PX4 controls
        rate = max(-RO_YAW_RATE_LIM, min(RO_YAW_RATE_LIM, RO_YAW_P * err))
        brake = math.sqrt(2.0 * YAW_ACCEL_LIM * BRAKE_FRACTION * abs(err))  # stop at the bearing
        rate = max(-brake, min(brake, rate))
        v = max(abs(s.speed), 0.3)
        cap = TURN_RATE_AT_1MPS * math.sqrt(max(self._speed_ramped, 0.3))
        rate = max(-cap, min(cap, rate))
        step = YAW_ACCEL_LIM * self.loop_dt
        rate = max(self._rate_sp - step, min(self._rate_sp + step, rate))
        self._rate_sp = rate
        delta = math.atan(rate * SihRover.WHEELBASE_M / v)
        return max(-1.0, min(1.0, delta / SihRover.MAX_STEER_RAD))

    def _targets(self) -> tuple[float, float]:
        """(speed m/s, NED yaw) the rover loops aim at in the current mode."""
        s = self.state
        if not self.armed:
            return 0.0, s.estimated_yaw
        mode = self.mode
        if mode == "OFFBOARD":
            return min(self._speed, RO_SPEED_LIM), self._bearing
        if mode == "LOITER" and self._hold_point is not None:
            r, direction = self._drift  # the estimate = the truth + the drift
            est_n, est_e = s.north + r * math.cos(direction), s.east + r * math.sin(direction)
            dn, de = self._hold_point[0] - est_n, self._hold_point[1] - est_e
            d = math.hypot(dn, de)
            if d > HOLD_RADIUS_M:  # drive back to where Hold was engaged
                self._hold_yaw = None
                bearing = math.atan2(de, dn)
                return min(
                    HOLD_SPEED, max(HOLD_MIN_SPEED, HOLD_GAIN * (d - HOLD_RADIUS_M))
                ), bearing
        if self._hold_yaw is None:
            self._hold_yaw = s.estimated_yaw  # brake straight, holding the heading
        return 0.0, self._hold_yaw
