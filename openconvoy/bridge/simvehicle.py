"""A simulated vehicle that speaks MAVLink like ArduPilot Rover (GUIDED) or PX4 (OFFBOARD).

Real MAVLink bytes through pymavlink, driven in real time by the simulator's plant
(``envs.plant.BicyclePlant`` with a vehicle preset), with GPS coordinates around a home
position. It reproduces shared/AUTOPILOTS.md, with the start-up delays configurable and
shorter by default:

- heartbeat: type 10 (ground rover), autopilot 3 or 12, ``custom_mode`` (ArduPilot mode
  number; PX4 ``main << 16 | sub << 24``), armed bit 128; 1 Hz;
- arming refused (COMMAND_ACK result 4 after a STATUSTEXT reason) until the estimator is
  ready (``ready_after_s``); LOCAL_NED setpoints ignored until the EKF has an origin;
- ArduPilot: setpoints ignored outside GUIDED, dropped when the acceleration bits are not
  all "ignore"; velocity + yaw gives heading from yaw and speed |v| (capped by WP_SPEED),
  velocity only gives heading atan2(vy, vx); no setpoint for ``setpoint_timeout_s`` (3 s)
  -> stop, staying in GUIDED;
- PX4: OFFBOARD (and arming in it) refused unless setpoints stream above 2 Hz for more
  than 1 s; when the stream drops below 2 Hz, OFFBOARD is left after ``offboard_loss_s``
  (COM_OF_LOSS_T) for the failsafe, AUTO.LOITER (hold);
- SET_MESSAGE_INTERVAL accepted up to ``max_message_hz``, refused (result 4) above it;
- test hooks: ``freeze`` (stop sending), ``stop`` (a killed vehicle), ``pilot_set_mode``
  (a person flips the mode switch); in the process form SIGUSR1 switches to MANUAL and
  SIGUSR2 toggles the freeze (SIGSTOP/SIGKILL freeze or kill the whole process).

Use in-process (``SimVehicle(...).start()`` runs a background thread) or as a process
(``openconvoy vehicle --sim``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from openconvoy.bridge import mavproto as mp
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState, wrap_angle
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.vehicles import VEHICLE_PRESETS, VehiclePreset

_STREAM_MIN_HZ = 2.0  # PX4: the offboard stream must stay above this rate
_STREAM_WARMUP_S = 1.0  # PX4 v1.16+: ... for more than this long before OFFBOARD
_TELEMETRY_IDS = (
    mp.MSG_GLOBAL_POSITION_INT, mp.MSG_ATTITUDE, mp.MSG_VFR_HUD, mp.MSG_LOCAL_POSITION_NED,
)

DEFAULT_HOME = Origin(52.0, 4.37, 0.0)
"""Home position used when none is given (an open field; any would do)."""


@dataclass(frozen=True)
class SimVehicleConfig:
    """How a simulated vehicle behaves. Times in seconds, rates in Hz, speeds in m/s.

    Attributes:
        system_id: MAVLink system id (the ``--id``).
        autopilot: ``"ardupilot"`` (Rover, GUIDED) or ``"px4"`` (OFFBOARD).
        preset: the vehicle + inner loops (speed lag, accel limits, turn rate, delay).
        home: geodetic home; the plant's ENU frame is tangent there.
        start_x_m, start_y_m, start_heading_rad: initial ENU pose around home.
        ready_after_s: time after boot until the estimator allows arming (real: ~40 s).
        ekf_origin_after_s: time after boot until LOCAL_NED setpoints are accepted
            (real: ~20 s); None = half of ``ready_after_s``.
        setpoint_timeout_s: ArduPilot GUIDED stops after this long without a setpoint.
        offboard_loss_s: PX4 COM_OF_LOSS_T: leave OFFBOARD this long after the stream
            dropped below 2 Hz.
        max_message_hz: fastest telemetry rate SET_MESSAGE_INTERVAL accepts.
        default_message_hz: telemetry rate before any request.
        wp_speed_mps: ArduPilot WP_SPEED speed cap.
        plant_hz: plant step rate.
        gps_noise_m: standard deviation of position noise on GLOBAL_POSITION_INT.
        seed: seeds the noise.
    """

    system_id: int = 1
    autopilot: Literal["ardupilot", "px4"] = "ardupilot"
    preset: VehiclePreset = field(default_factory=lambda: VEHICLE_PRESETS["1/10"])
    home: Origin = DEFAULT_HOME
    start_x_m: float = 0.0
    start_y_m: float = 0.0
    start_heading_rad: float = 0.0
    ready_after_s: float = 5.0
    ekf_origin_after_s: float | None = None
    setpoint_timeout_s: float = 3.0
    offboard_loss_s: float = 1.0
    max_message_hz: float = 40.0
    default_message_hz: float = 1.0
    wp_speed_mps: float = 5.0
    plant_hz: float = 50.0
    gps_noise_m: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.autopilot not in ("ardupilot", "px4"):
            raise ConfigError(f"autopilot must be 'ardupilot' or 'px4', got {self.autopilot!r}")
        if not 1 <= self.system_id <= 254:
            raise ConfigError(f"MAVLink system id must be in 1..254, got {self.system_id}")
        if self.ready_after_s < 0 or self.setpoint_timeout_s <= 0 or self.plant_hz <= 0:
            raise ConfigError("ready_after_s >= 0, setpoint_timeout_s > 0 and plant_hz > 0 required")


class SimVehicle:
    """One simulated autopilot + vehicle on a MAVLink URL (e.g. ``udpin:127.0.0.1:14551``).

    ``start`` opens the link and runs the vehicle in a daemon thread in real time; ``stop``
    ends it and closes the socket (a killed vehicle). Thread-safe accessors for tests:
    ``state``, ``mode``, ``armed``, ``setpoints_received``.
    """

    def __init__(
        self,
        url: str,
        config: SimVehicleConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.url = url
        self.config = config or SimVehicleConfig()
        self._clock = clock
        c = self.config
        self._plant = BicyclePlant([c.preset], dt=1.0 / c.plant_hz)
        self._plant.reset(
            np.array([c.start_x_m]), np.array([c.start_y_m]), np.array([c.start_heading_rad])
        )
        self._rng = np.random.default_rng(c.seed)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._conn: Any = None
        self._frozen = False
        self._armed = False
        self._mode = "HOLD" if c.autopilot == "ardupilot" else "LOITER"
        self._pending_mode: str | None = None  # set from other threads (pilot, signals)
        self._sp: tuple[float, float] | None = None  # (speed, ENU heading) of last setpoint
        self._t_sp = -math.inf
        self._stream_since = -math.inf
        self._t_stream_lost: float | None = None
        self.setpoints_received = 0
        """Setpoints accepted (not ignored or dropped) so far."""
        self.setpoints_ignored = 0
        """Setpoints ignored (wrong mode, no EKF origin) or dropped (acceleration bits)."""
        self._intervals: dict[int, float] = {m: 1.0 / c.default_message_hz for m in _TELEMETRY_IDS}
        self._due: dict[int, float] = {}
        self._t_boot = 0.0
        self._t_plant = 0.0
        self._t_heartbeat = -math.inf
        self._heard_peer = False

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> SimVehicle:
        """Open the MAVLink link and start the vehicle thread; returns self."""
        self._conn = mp.mavutil.mavlink_connection(
            self.url, source_system=self.config.system_id, source_component=1
        )
        self._t_boot = self._clock()
        self._t_plant = self._t_boot
        self._stop_evt.clear()
        self._thread = threading.Thread(
            target=self._run, name=f"simvehicle-{self.config.system_id}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close the socket at once (what a killed vehicle does)."""
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None

    def request_stop(self) -> None:
        """Ask the thread to end (safe from signal handlers); ``stop`` then cleans up."""
        self._stop_evt.set()

    def __enter__(self) -> SimVehicle:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run_forever(self) -> None:
        """Start and block until ``stop`` (the process form)."""
        if self._thread is None:
            self.start()
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=0.2)

    # ----------------------------------------------------------------- test hooks

    def freeze(self, frozen: bool = True) -> None:
        """Stop (True) or resume (False) sending anything: telemetry, heartbeats, ACKs."""
        self._frozen = frozen

    @property
    def frozen(self) -> bool:
        return self._frozen

    def pilot_set_mode(self, mode: str) -> None:
        """A person changes the mode (RC switch or GCS), e.g. ``"MANUAL"``."""
        known = mp.ROVER_MODE_NUMBERS if self.config.autopilot == "ardupilot" else mp.PX4_MODE_NUMBERS
        if mode not in known:
            raise ConfigError(f"unknown {self.config.autopilot} mode {mode!r}; one of {', '.join(known)}")
        self._pending_mode = mode

    # ----------------------------------------------------------------- accessors

    def state(self) -> VehicleState:
        """Ground truth: ENU around home, the vehicle clock's seconds since boot."""
        with self._lock:
            return self._plant.state(0, self._clock() - self._t_boot)

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def message_rates_hz(self) -> dict[str, float]:
        """Current telemetry rate per message name (0 = disabled)."""
        return {
            mp.message_name(m): (0.0 if iv <= 0 else 1.0 / iv) for m, iv in self._intervals.items()
        }

    # ----------------------------------------------------------------- the loop

    def _now(self) -> float:
        return self._clock() - self._t_boot

    def _run(self) -> None:
        dt = self._plant.dt
        while not self._stop_evt.is_set():
            try:
                self._receive()
            except OSError:
                pass  # a peer went away (TCP); keep simulating, as firmware would
            if self._pending_mode is not None:
                mode, self._pending_mode = self._pending_mode, None
                self._enter_mode(mode, by_pilot=True)
            t = self._now()
            self._supervise(t)
            steps = 0
            while self._clock() - self._t_plant >= dt and steps < 25:
                speed, heading = self._target()
                with self._lock:
                    self._plant.step(np.array([speed]), np.array([heading]))
                self._t_plant += dt
                steps += 1
            if self._clock() - self._t_plant > 0.5:  # fell far behind (debugger, SIGSTOP)
                self._t_plant = self._clock()
            if not self._frozen:
                self._send_due(t)
            self._stop_evt.wait(max(0.0, self._t_plant + dt - self._clock()))

    def _target(self) -> tuple[float, float]:
        """The (speed, heading) the inner loops aim at now."""
        heading = float(self._plant.heading[0])
        if not self._armed or self._sp is None:
            return 0.0, heading
        if self.config.autopilot == "ardupilot":
            if self._mode != "GUIDED" or self._now() - self._t_sp > self.config.setpoint_timeout_s:
                return 0.0, heading  # GUIDED without setpoints stops (and stays in GUIDED)
        elif self._mode != "OFFBOARD":
            return 0.0, heading
        return self._sp

    def _supervise(self, t: float) -> None:
        """PX4's offboard-loss failsafe."""
        if self.config.autopilot != "px4" or self._mode != "OFFBOARD":
            self._t_stream_lost = None
            return
        if t - self._t_sp <= 1.0 / _STREAM_MIN_HZ:
            self._t_stream_lost = None
            return
        if self._t_stream_lost is None:
            self._t_stream_lost = self._t_sp + 1.0 / _STREAM_MIN_HZ
        if t - self._t_stream_lost >= self.config.offboard_loss_s:
            self._text(2, "Failsafe: offboard control lost, activating Hold")
            self._enter_mode("LOITER", by_pilot=False)

    def _enter_mode(self, mode: str, by_pilot: bool) -> None:
        self._mode = mode
        if by_pilot:
            self._text(6, f"Mode changed to {mode}")

    def _estimator_ready(self) -> bool:
        return self._now() >= self.config.ready_after_s

    def _ekf_origin(self) -> bool:
        after = self.config.ekf_origin_after_s
        if after is None:
            after = self.config.ready_after_s / 2
        return self._now() >= after

    def _stream_ok(self) -> bool:
        t = self._now()
        return t - self._t_sp <= 1.0 / _STREAM_MIN_HZ and t - self._stream_since > _STREAM_WARMUP_S

    # ----------------------------------------------------------------- receiving

    def _receive(self) -> None:
        conn = self._conn
        for _ in range(1000):
            msg = conn.recv_msg()
            if msg is None:
                return
            kind = msg.get_type()
            if not self._heard_peer:
                # A listening (udpin/tcpin) vehicle can only answer once it heard someone:
                # send the first heartbeat now rather than up to 1 s later.
                self._heard_peer = True
                self._t_heartbeat = -math.inf
            if kind == "COMMAND_LONG":
                if msg.target_system in (0, self.config.system_id):
                    self._on_command(msg)
            elif kind in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"):
                if msg.target_system in (0, self.config.system_id):
                    self._on_setpoint(msg, local=kind.endswith("LOCAL_NED"))

    def _ack(self, msg: Any, result: int) -> None:
        if self._frozen:
            return
        self._conn.mav.command_ack_send(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )

    def _text(self, severity: int, text: str) -> None:
        if self._frozen or self._conn is None:
            return
        self._conn.mav.statustext_send(severity, text.encode()[:50])

    def _on_command(self, msg: Any) -> None:
        cmd = msg.command
        if cmd == mp.CMD_DO_SET_MODE:
            self._ack(msg, self._on_set_mode(msg))
        elif cmd == mp.CMD_COMPONENT_ARM_DISARM:
            self._ack(msg, self._on_arm(msg.param1 > 0.5))
        elif cmd == mp.CMD_SET_MESSAGE_INTERVAL:
            self._ack(msg, self._on_interval(int(msg.param1), msg.param2))
        else:
            self._ack(msg, mp.RESULT_UNSUPPORTED)

    def _on_set_mode(self, msg: Any) -> int:
        if self.config.autopilot == "ardupilot":
            name = mp.ROVER_MODES.get(int(msg.param2))
            if name is None:
                return mp.RESULT_FAILED
        else:
            name = mp.PX4_MODES.get((int(msg.param2), int(msg.param3)))
            if name is None:
                return mp.RESULT_DENIED
            if name == "OFFBOARD" and self._mode != "OFFBOARD" and not self._stream_ok():
                self._text(2, "Switching to Offboard is currently not available")
                return mp.RESULT_TEMPORARILY_REJECTED
        self._enter_mode(name, by_pilot=False)
        return mp.RESULT_ACCEPTED

    def _on_arm(self, arm: bool) -> int:
        if not arm:
            self._armed = False
            return mp.RESULT_ACCEPTED
        if self._armed:
            return mp.RESULT_ACCEPTED
        if not self._estimator_ready():
            if self.config.autopilot == "ardupilot":
                self._text(2, "PreArm: AHRS: not using configured AHRS type")
            else:
                self._text(2, "Preflight Fail: ekf2 not ready (no GPS fusion yet)")
            return mp.RESULT_FAILED
        if self.config.autopilot == "px4" and self._mode == "OFFBOARD" and not self._stream_ok():
            self._text(2, "Arming denied: offboard signal lost")
            return mp.RESULT_DENIED
        self._armed = True
        return mp.RESULT_ACCEPTED

    def _on_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id not in _TELEMETRY_IDS:
            return mp.RESULT_FAILED
        if interval_us < 0:
            self._intervals[msg_id] = 0.0  # disabled
        elif interval_us == 0:
            self._intervals[msg_id] = 1.0 / self.config.default_message_hz
        else:
            if 1e6 / interval_us > self.config.max_message_hz + 1e-9:
                return mp.RESULT_FAILED  # faster than the scheduler loop: refused
            self._intervals[msg_id] = interval_us * 1e-6
        self._due.pop(msg_id, None)
        return mp.RESULT_ACCEPTED

    def _on_setpoint(self, msg: Any, local: bool) -> None:
        t = self._now()
        mask = msg.type_mask
        if self.config.autopilot == "px4":
            # PX4 counts every setpoint message towards the offboard stream's health.
            if t - self._t_sp > 1.0 / _STREAM_MIN_HZ:
                self._stream_since = t
            self._t_sp = t
        ignored = (
            (mask & mp.MASK_ACC) != mp.MASK_ACC  # acceleration in use: dropped
            or (mask & mp.MASK_VEL) != 0  # only velocity setpoints are modelled
            or (local and not self._ekf_origin() and self.config.autopilot == "ardupilot")
            or (self.config.autopilot == "ardupilot" and self._mode != "GUIDED")
        )
        if ignored:
            self.setpoints_ignored += 1
            return
        vn, ve = float(msg.vx), float(msg.vy)
        speed = math.hypot(vn, ve)
        if not mask & mp.MASK_YAW:
            heading = wrap_angle(math.pi / 2 - float(msg.yaw))
            if self.config.autopilot == "ardupilot":
                if vn <= -1.1920929e-07:  # Rover: is_negative(vx) alone reverses (sitl/ row 7)
                    speed = -speed
            elif vn * math.cos(msg.yaw) + ve * math.sin(msg.yaw) < 0:
                speed = -speed  # velocity against the yaw: reverse
        elif not mask & mp.MASK_YAW_RATE:
            # Velocity + yaw rate: aim a short way ahead of the current heading.
            heading = wrap_angle(float(self._plant.heading[0]) - float(msg.yaw_rate) * 0.5)
        else:
            # Velocity only: heading atan2 of the vector (a zero vector means north).
            heading = wrap_angle(math.pi / 2 - math.atan2(ve, vn))
        speed = max(-self.config.wp_speed_mps, min(self.config.wp_speed_mps, speed))
        self._sp = (speed, heading)
        if self.config.autopilot == "ardupilot":
            self._t_sp = t
        self.setpoints_received += 1

    # ----------------------------------------------------------------- sending

    def _send_due(self, t: float) -> None:
        mav = self._conn.mav
        if t - self._t_heartbeat >= 1.0:
            self._t_heartbeat = t
            self._heartbeat(mav)
        for msg_id, interval in self._intervals.items():
            if interval <= 0:
                continue
            due = self._due.get(msg_id, t)
            if t + 1e-6 < due:
                continue
            # Keep the schedule's phase unless we fell behind by more than one period.
            self._due[msg_id] = due + interval if t - due < interval else t + interval
            self._send_telemetry(mav, msg_id, t)

    def _heartbeat(self, mav: Any) -> None:
        c = self.config
        base = mp.mav().MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base |= mp.mav().MAV_MODE_FLAG_SAFETY_ARMED
        if c.autopilot == "ardupilot":
            autopilot, custom = mp.AUTOPILOT_ARDUPILOT, mp.ROVER_MODE_NUMBERS[self._mode]
        else:
            autopilot, custom = mp.AUTOPILOT_PX4, mp.px4_custom_mode(*mp.PX4_MODE_NUMBERS[self._mode])
        status = mp.mav().MAV_STATE_ACTIVE if self._armed else mp.mav().MAV_STATE_STANDBY
        mav.heartbeat_send(mp.MAV_TYPE_GROUND_ROVER, autopilot, base, custom, status)

    def _send_telemetry(self, mav: Any, msg_id: int, t: float) -> None:
        with self._lock:
            x, y = float(self._plant.x[0]), float(self._plant.y[0])
            h, v = float(self._plant.heading[0]), float(self._plant.speed[0])
            yaw_rate = float(self._plant.yaw_rate[0])
        t_ms = int(t * 1000) & 0xFFFFFFFF
        yaw = wrap_angle(math.pi / 2 - h)
        vn, ve = v * math.sin(h), v * math.cos(h)
        if msg_id == mp.MSG_GLOBAL_POSITION_INT:
            if self.config.gps_noise_m > 0:
                x += float(self._rng.normal(0.0, self.config.gps_noise_m))
                y += float(self._rng.normal(0.0, self.config.gps_noise_m))
            lat, lon, alt = enu_to_geodetic(self.config.home, x, y, 0.0)
            mav.global_position_int_send(
                t_ms, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), 0,
                int(round(vn * 100)), int(round(ve * 100)), 0,
                int(round(math.degrees(yaw) * 100)) % 36000,
            )
        elif msg_id == mp.MSG_ATTITUDE:
            mav.attitude_send(t_ms, 0.0, 0.0, yaw, 0.0, 0.0, -yaw_rate)
        elif msg_id == mp.MSG_VFR_HUD:
            mav.vfr_hud_send(abs(v), abs(v), int(math.degrees(yaw)) % 360, 0, 0.0, 0.0)
        elif msg_id == mp.MSG_LOCAL_POSITION_NED and self._ekf_origin():
            mav.local_position_ned_send(t_ms, y, x, 0.0, vn, ve, 0.0)


# --------------------------------------------------------------------- process form (CLI)


def _floats(text: str, n: int, what: str, example: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{what} must be {n} comma-separated finite numbers like {example}, got {text!r}")
    return values


def parse_home(text: str) -> Origin:
    """``LAT,LON,ALT`` (degrees, degrees, metres) -> Origin; ``LAT,LON`` means altitude 0."""
    if text.count(",") == 1:
        text += ",0"
    lat, lon, alt = _floats(text, 3, "--home", "52.0,4.37,0")
    return Origin(lat, lon, alt)


def parse_start(text: str) -> tuple[float, float, float]:
    """``X,Y,HEADING_DEG`` (ENU metres around home; heading degrees, 0 = east, CCW) ->
    (x_m, y_m, heading_rad)."""
    x, y, heading_deg = _floats(text, 3, "--start", "0,0,90")
    return x, y, math.radians(heading_deg)


def _check_port_free(url: str) -> None:
    """A ``udpin:`` port another process holds is refused (pymavlink binds with
    SO_REUSEADDR, so two vehicles would otherwise share it silently)."""
    if not url.startswith("udpin:"):
        return
    import socket

    host, _, port = url.split(":", 1)[1].rpartition(":")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, int(port)))
    except OSError as exc:
        raise ConfigError(f"--mavlink {url}: cannot listen there ({exc.strerror or exc}; another vehicle on this port?)") from None
    finally:
        probe.close()


def run_vehicle_cli(args: Any) -> int:
    """``openconvoy vehicle --sim``: run one simulated vehicle until SIGINT/SIGTERM.

    Prints one ready line to stdout. SIGUSR1: a person switches to MANUAL; SIGUSR2:
    toggle the telemetry freeze."""
    import signal

    from openconvoy.bridge.mavlink import check_url
    from openconvoy.envs.vehicles import vehicle_preset

    if not args.sim:
        raise ConfigError("only simulated vehicles exist here: add --sim (a real vehicle runs its own autopilot)")
    check_url(args.mavlink)
    _check_port_free(args.mavlink)
    x, y, heading = parse_start(args.start)
    config = SimVehicleConfig(
        system_id=args.id, autopilot=args.autopilot, preset=vehicle_preset(args.preset),
        home=parse_home(args.home), start_x_m=x, start_y_m=y, start_heading_rad=heading,
        ready_after_s=args.ready_after, setpoint_timeout_s=args.setpoint_timeout,
        max_message_hz=args.max_rate, gps_noise_m=args.gps_noise, seed=args.seed,
    )
    vehicle = SimVehicle(args.mavlink, config)
    try:
        vehicle.start()
    except OSError as exc:
        raise ConfigError(f"cannot open {args.mavlink}: {exc}") from exc

    signal.signal(signal.SIGTERM, lambda s, f: vehicle.request_stop())
    signal.signal(signal.SIGINT, lambda s, f: vehicle.request_stop())
    signal.signal(signal.SIGUSR1, lambda s, f: vehicle.pilot_set_mode("MANUAL"))
    signal.signal(signal.SIGUSR2, lambda s, f: vehicle.freeze(not vehicle.frozen))
    h = config.home
    print(
        f"vehicle {config.system_id}: simulated {config.autopilot} {config.preset.name} on "
        f"{args.mavlink}, home {h.lat_deg:.7f},{h.lon_deg:.7f},{h.alt_m:g}, "
        f"arming possible after {config.ready_after_s:g} s",
        flush=True,
    )
    vehicle.run_forever()
    vehicle.stop()
    return 0
