"""A simulated vehicle that speaks MAVLink like ArduPilot Rover (GUIDED) or PX4 (OFFBOARD).

Real MAVLink bytes through pymavlink around a firmware model fitted to recordings of the
real firmware: ``simvehicle.ardupilot.ArduPilotRover`` (shared/sitl/, ArduPilot Rover 4.7 SITL)
and ``simvehicle.px4.Px4Rover`` (shared/sitl-px4/, PX4 SIH rover). Each one models the
firmware's mode logic, arming checks, setpoint semantics, failsafes and message-rate
rules; the motion under it is pluggable (``simvehicle.motion``): by default the firmware's own
loops drive the vehicle model its recordings were made with (SITL rover, SIH rover), or,
with ``preset=``, the simulator's plant with that vehicle preset.

This module is the shell: the MAVLink connection, COMMAND_ACKs, and the clock; the
heartbeat and telemetry streams (on the firmware's 50 Hz scheduler, so 20 Hz comes as
alternating 40/60 ms intervals, all messages in one burst) and STATUSTEXTs (split into
50-character chunks) are ``simvehicle.streams``:

- real time in a background thread (``start``), optionally ``speedup`` times faster;
- lockstep (``open`` then ``advance(dt)``): the caller moves the vehicle's clock, so a
  replay runs as fast as the CPU allows (the conformance tests).

``timing="firmware"`` reproduces the recorded boot and arming timeline (ArduPilot: arm
in MANUAL ~23 s, in GUIDED ~42 s after boot); the default ``"short"`` keeps its order,
compressed so that GUIDED/OFFBOARD is armable after ``ready_after_s``. ArduPilot's RC
mode switch at boot (MANUAL 0.42 s after "ArduPilot Ready") is on by default.

With a ``world`` (``simvehicle.world.SimWorld``) and a preset carrying a ranging sensor, the
vehicle streams DISTANCE_SENSOR as a forward rangefinder would (orientation 0, laser, cm
from the front bumper to the nearest vehicle ahead, max + 1 m when nothing is in range)
at ``simvehicle.streams.RANGE_HZ``; without a world it has no rangefinder.

Test hooks: ``freeze`` (stop sending), ``stop`` (a killed vehicle), ``pilot_set_mode``
(a person flips the mode switch); in the process form SIGUSR1 switches to MANUAL and
SIGUSR2 toggles the freeze.
"""

from __future__ import annotations

import dataclasses
import math
import select
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.ardupilot import ArduPilotRover, ArduPilotTiming
from openconvoy.bridge.simvehicle.motion import MotionState, PresetMotion
from openconvoy.bridge.simvehicle.px4 import Px4Rover, Px4Timing
from openconvoy.bridge.simvehicle.streams import MSG_HEARTBEAT, SimStreams
from openconvoy.bridge.simvehicle.world import SimWorld
from openconvoy.comms.geodesy import Origin
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState, wrap_angle
from openconvoy.envs.vehicles import VehiclePreset

DEFAULT_HOME = Origin(52.0, 4.37, 0.0)
"""Home position used when none is given (an open field; any would do)."""


@dataclass(frozen=True)
class SimVehicleConfig:
    """How a simulated vehicle behaves. Times in seconds, rates in Hz, speeds in m/s.

    Attributes:
        system_id: MAVLink system id (the ``--id``).
        autopilot: ``"ardupilot"`` (Rover, GUIDED) or ``"px4"`` (OFFBOARD).
        preset: None = the firmware's loops on the recorded firmware's vehicle model;
            a preset = the simulator's plant with it (its lags, limits and delay).
        home: geodetic home; the ENU frame is tangent there.
        start_x_m, start_y_m, start_heading_rad: initial ENU pose around home.
        timing: ``"short"`` (the boot order compressed to ``ready_after_s``) or
            ``"firmware"`` (the recorded timeline; ``ready_after_s`` unused).
        ready_after_s: short timing: GUIDED/OFFBOARD armable this long after boot.
        init_s: ArduPilot, short timing: "ArduPilot Ready" (INITIAL_MODE, then the RC
            switch 0.42 s later) at this time instead of the compressed one.
        ekf_origin_after_s: short timing: LOCAL_NED setpoints accepted from then
            (None = the compressed firmware time).
        rc_mode_switch: ArduPilot: the RC mode switch's first reading sets MANUAL.
        setpoint_timeout_s: ArduPilot GUIDED stops after this long without a setpoint.
        offboard_loss_s: PX4 COM_OF_LOSS_T.
        offboard_loss_action: PX4 COM_OBL_RC_ACT: 0 POSCTL (brake), 5 Hold (loiter).
        max_message_hz: refuse SET_MESSAGE_INTERVAL above this (None = the firmware's
            rule: ArduPilot refuses rates >= SCHED_LOOP_RATE 50 Hz, PX4 none).
        default_message_hz: telemetry rate before any request.
        wp_speed_mps: ArduPilot WP_SPEED speed cap.
        plant_hz: plant step rate with a preset.
        speedup: real-time form: the vehicle's clock runs this many times faster.
        boot_on_connect: real-time form: boot when the first MAVLink message arrives (as
            SITL waiting for its serial0 connection), so a companion that connects at once
            meets the whole boot sequence.
        gps_noise_m: standard deviation of position noise on GLOBAL_POSITION_INT.
        heading_bias_max_deg: PX4: the estimator's heading error, drawn once per vehicle and
            run (this seed) uniformly within +- this (deg); it steers and reports the
            biased heading (``px4``; sitl-px4 shows up to ~10°). 0 = none.
        px4_clock_ratio: PX4: its clock's seconds per real second (None: the timing's:
            SIH's 0.990 with ``firmware``, 1 with ``short``).
        seed: seeds the noise and the heading bias.
        other_streams_hz: messages/s of the firmware's other onboard streams (0 = none;
            a real PX4 sends ~200/s besides what is requested, shared/sitl-px4): what fills
            a companion's socket buffer while its loop pauses.
        hold_drift_mps: PX4: how fast the position estimate drifts while held (m/s; 0 =
            none). Its Hold drives back to the hold point as the estimate sees it, so a
            drift past the acceptance radius moves the vehicle: the loops at up to 2.2 m/s
            of 2 in 14 held firmware vehicles (shared/AUTOPILOTS.md, issue 22's PX4 HOLD).
    """

    system_id: int = 1
    autopilot: Literal["ardupilot", "px4"] = "ardupilot"
    preset: VehiclePreset | None = None
    home: Origin = DEFAULT_HOME
    start_x_m: float = 0.0
    start_y_m: float = 0.0
    start_heading_rad: float = 0.0
    timing: Literal["short", "firmware"] = "short"
    ready_after_s: float = 5.0
    init_s: float | None = None
    ekf_origin_after_s: float | None = None
    rc_mode_switch: bool = True
    setpoint_timeout_s: float = 3.0
    offboard_loss_s: float = 1.0
    offboard_loss_action: int = 0
    max_message_hz: float | None = None
    default_message_hz: float = 1.0
    wp_speed_mps: float = 5.0
    plant_hz: float = 50.0
    speedup: float = 1.0
    boot_on_connect: bool = False
    gps_noise_m: float = 0.0
    heading_bias_max_deg: float = 0.0
    px4_clock_ratio: float | None = None
    seed: int = 0
    other_streams_hz: float = 0.0
    hold_drift_mps: float = 0.0

    def __post_init__(self) -> None:
        if self.autopilot not in ("ardupilot", "px4"):
            raise ConfigError(f"autopilot must be 'ardupilot' or 'px4', got {self.autopilot!r}")
        if self.timing not in ("short", "firmware"):
            raise ConfigError(f"timing must be 'short' or 'firmware', got {self.timing!r}")
        if not 1 <= self.system_id <= 254:
            raise ConfigError(f"MAVLink system id must be in 1..254, got {self.system_id}")
        if self.ready_after_s < 0 or self.setpoint_timeout_s <= 0 or self.plant_hz <= 0:
            raise ConfigError(
                "ready_after_s >= 0, setpoint_timeout_s > 0 and plant_hz > 0 required"
            )
        if self.speedup <= 0:
            raise ConfigError(f"speedup must be positive, got {self.speedup}")
        if self.px4_clock_ratio is not None and not 0.5 <= self.px4_clock_ratio <= 2.0:
            raise ConfigError(f"px4_clock_ratio must be in [0.5, 2], got {self.px4_clock_ratio}")
        if not 0.0 <= self.heading_bias_max_deg <= 45.0:
            raise ConfigError(
                f"heading_bias_max_deg must be in [0, 45], got {self.heading_bias_max_deg}"
            )
        if self.offboard_loss_action not in (0, 5):
            raise ConfigError(
                f"offboard_loss_action must be 0 (POSCTL) or 5 (Hold), got {self.offboard_loss_action}"
            )

    @property
    def armable_after_s(self) -> float:
        """When GUIDED (ArduPilot) or OFFBOARD (PX4) arming is first accepted."""
        if self.autopilot == "px4":
            t = (
                Px4Timing.firmware()
                if self.timing == "firmware"
                else Px4Timing.short(self.ready_after_s)
            )
            return t.armable_s
        return self._ardupilot_timing().ekf_gps_s

    def _ardupilot_timing(self) -> ArduPilotTiming:
        if self.timing == "firmware":
            return ArduPilotTiming.firmware()
        t = ArduPilotTiming.short(self.ready_after_s, self.init_s)
        if self.ekf_origin_after_s is not None:
            from dataclasses import replace

            t = replace(
                t, origin_s=self.ekf_origin_after_s, gps_s=min(t.gps_s, self.ekf_origin_after_s)
            )
        return t


def make_firmware(config: SimVehicleConfig, state: MotionState) -> ArduPilotRover | Px4Rover:
    """The firmware model (and its motion) a config asks for."""
    c = config
    motion = PresetMotion(state, c.preset, 1.0 / c.plant_hz) if c.preset is not None else None
    if c.autopilot == "ardupilot":
        return ArduPilotRover(
            state,
            c._ardupilot_timing(),
            rc_mode_switch=c.rc_mode_switch,
            wp_speed_mps=c.wp_speed_mps,
            setpoint_timeout_s=c.setpoint_timeout_s,
            motion=motion,
        )
    timing = Px4Timing.firmware() if c.timing == "firmware" else Px4Timing.short(c.ready_after_s)
    if c.px4_clock_ratio is not None:
        timing = dataclasses.replace(timing, clock_ratio=c.px4_clock_ratio)
    fw = Px4Rover(
        state,
        timing,
        c.home.lat_deg,
        c.home.lon_deg,
        obl_rc_act=c.offboard_loss_action,
        motion=motion,
        hold_drift_mps=c.hold_drift_mps,
    )
    fw.params["COM_OF_LOSS_T"] = c.offboard_loss_s
    return fw


class SimVehicle:
    """One simulated autopilot + vehicle on a MAVLink URL (e.g. ``udpin:127.0.0.1:14551``).

    ``start`` opens the link and runs the vehicle in a daemon thread in real time
    (times ``config.speedup``); ``stop`` ends it and closes the socket (a killed vehicle).
    Lockstep instead: ``open()``, then ``advance(dt)`` as often as wanted. Thread-safe
    accessors for tests: ``state``, ``mode``, ``armed``, ``setpoints_received``.
    """

    def __init__(
        self,
        url: str,
        config: SimVehicleConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        world: SimWorld | None = None,
    ) -> None:
        self.url = url
        self.config = config or SimVehicleConfig()
        self._clock = clock
        c = self.config
        yaw = wrap_angle(math.pi / 2 - c.start_heading_rad)
        self._rng = np.random.default_rng(c.seed)
        bias = 0.0
        if c.autopilot == "px4" and c.heading_bias_max_deg > 0.0:
            # Its own stream: the noise draws stay as they were without a bias.
            draw = np.random.default_rng([c.seed, 0x48424941])  # "HBIA"
            bias = math.radians(float(draw.uniform(-1.0, 1.0)) * c.heading_bias_max_deg)
        self.motion_state = MotionState(north=c.start_y_m, east=c.start_x_m, yaw=yaw, yaw_bias=bias)
        self.firmware = make_firmware(c, self.motion_state)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._conn: Any = None
        self._frozen = False
        self._pending_mode: str | None = None  # set from other threads (pilot, signals)
        self._t = 0.0  # vehicle time since boot (s): the loop's clock
        self._t_wall0 = 0.0
        self._heard_peer = False
        self._world = world
        sensor = c.preset.ranging if c.preset is not None and world is not None else None
        if world is not None:
            world.register(c.system_id, self.state, c.preset.length_m if c.preset else 0.0)
        ranging = (sensor, world) if sensor is not None and world is not None else None
        self._streams = SimStreams(
            c, self.firmware, self.motion_state, self._lock, self._rng, ranging
        )

    # ----------------------------------------------------------------- lifecycle

    def open(self) -> SimVehicle:
        """Open the MAVLink link without a thread (lockstep: drive it with ``advance``)."""
        self._conn = mp.mavutil.mavlink_connection(
            self.url, source_system=self.config.system_id, source_component=1
        )
        return self

    def start(self) -> SimVehicle:
        """Open the MAVLink link and start the real-time vehicle thread; returns self."""
        self.open()
        self._t_wall0 = self._clock()
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

    close = stop

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
        known = (
            mp.ROVER_MODE_NUMBERS if self.config.autopilot == "ardupilot" else mp.PX4_MODE_NUMBERS
        )
        if mode not in known:
            raise ConfigError(
                f"unknown {self.config.autopilot} mode {mode!r}; one of {', '.join(known)}"
            )
        self._pending_mode = mode

    # ----------------------------------------------------------------- accessors

    def state(self) -> VehicleState:
        """Ground truth: ENU around home, the vehicle's seconds since boot."""
        with self._lock:
            s = self.motion_state
            return VehicleState(
                vehicle_id=0,
                t=self._t,
                x=s.east,
                y=s.north,
                speed=s.speed,
                heading=wrap_angle(math.pi / 2 - s.yaw),
                accel=s.accel,
                yaw_rate=-s.yaw_rate,
            )

    @property
    def t(self) -> float:
        """Vehicle time since boot (s)."""
        return self._t

    @property
    def mode(self) -> str:
        return self.firmware.mode

    @property
    def armed(self) -> bool:
        return self.firmware.armed

    @property
    def setpoints_received(self) -> int:
        """Setpoints accepted (not ignored or dropped) so far."""
        return self.firmware.setpoints_received

    @property
    def setpoints_ignored(self) -> int:
        """Setpoints ignored (wrong mode, no EKF origin, invalid mask or frame)."""
        return self.firmware.setpoints_ignored

    @property
    def message_rates_hz(self) -> dict[str, float]:
        """Current telemetry rate per message name (0 = disabled)."""
        return self._streams.rates_hz()

    # ----------------------------------------------------------------- the loop

    def _run(self) -> None:
        dt = self.firmware.loop_dt
        speed = self.config.speedup
        if self.config.boot_on_connect:
            while not self._heard_peer and not self._stop_evt.is_set():
                self._receive(queue_only=True)
                self._stop_evt.wait(0.005)
            self._t_wall0 = self._clock()
        while not self._stop_evt.is_set():
            target = (self._clock() - self._t_wall0) * speed
            if target - self._t > 0.5:  # fell far behind (debugger, SIGSTOP): skip ahead
                self._t = target - dt
            self._service(target)
            wake = self._t_wall0 + (self._t + dt) / speed
            self._stop_evt.wait(max(0.0, wake - self._clock()))

    def advance(self, seconds: float) -> None:
        """Lockstep: receive what arrived, then run the firmware loop ``seconds`` on."""
        self._service(self._t + seconds)

    def advance_to(self, t: float) -> None:
        """Lockstep: receive, then run the firmware loop up to vehicle time ``t`` (s)."""
        self._service(t)

    def wait_readable(self, timeout_s: float) -> bool:
        """True when a datagram is waiting (lockstep callers use it after sending)."""
        port = getattr(self._conn, "port", None)
        if port is None:
            return False
        return bool(select.select([port], [], [], timeout_s)[0])

    def _service(self, until: float) -> None:
        """Receive, then run every loop tick up to vehicle time ``until``, sending what is
        due on each tick."""
        dt = self.firmware.loop_dt
        self._receive()
        if self._pending_mode is not None:
            mode, self._pending_mode = self._pending_mode, None
            self.firmware.pilot_set_mode(mode)
        while self._t + dt <= until + 1e-9:
            with self._lock:
                self.firmware.tick(self._t)
                self._t += dt
            self._flush_texts()
            if not self._frozen and self._t >= self.firmware.first_heartbeat_s:
                self._streams.send_due(self._conn.mav, self._t)

    # ----------------------------------------------------------------- receiving

    def _receive(self, queue_only: bool = False) -> None:
        """Handle what arrived; ``queue_only``: before boot, only notice the first peer
        (its datagrams stay queued for the booted autopilot)."""
        conn = self._conn
        if conn is None:
            return
        if queue_only:
            self._heard_peer = self.wait_readable(0.0)
            return
        for _ in range(1000):
            try:
                msg = conn.recv_msg()
            except OSError:
                return  # a peer went away (TCP); keep simulating, as firmware would
            if msg is None:
                return
            kind = msg.get_type()
            if not self._heard_peer:
                # A listening (udpin/tcpin) vehicle can only answer once it heard someone:
                # send the first heartbeat now rather than up to 1 s later.
                self._heard_peer = True
                self._streams.due.pop(MSG_HEARTBEAT, None)
            if kind == "COMMAND_LONG":
                if msg.target_system in (0, self.config.system_id):
                    self._on_command(msg)
            elif kind in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"):
                if (
                    msg.target_system in (0, self.config.system_id)
                    and self._t >= self.firmware.first_heartbeat_s
                ):
                    with self._lock:
                        self.firmware.setpoint(
                            self._t,
                            kind.endswith("LOCAL_NED"),
                            int(msg.coordinate_frame),
                            int(msg.type_mask),
                            float(msg.vx),
                            float(msg.vy),
                            float(msg.yaw),
                            float(msg.yaw_rate),
                        )
                    self._flush_texts()
            elif kind == "PARAM_SET" and msg.target_system in (0, self.config.system_id):
                self._on_param_set(msg)
            elif kind == "SET_MODE" and msg.target_system in (0, self.config.system_id):
                self._on_command(_SetModeCommand(msg, self.config.autopilot))

    def _on_param_set(self, msg: Any) -> None:
        setter = getattr(self.firmware, "param_set", None)
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
        value = float(msg.param_value)
        if msg.param_type in (1, 2, 3, 4, 5, 6):  # integers travel as their raw bytes
            value = float(struct.unpack("<i", struct.pack("<f", value))[0])
        stored = setter(name, value) if setter else None
        if stored is not None and not self._frozen:
            self._conn.mav.param_value_send(name.encode(), stored, msg.param_type, 0, 0)

    def _ack(self, msg: Any, result: int) -> None:
        if self._frozen:
            return
        self._conn.mav.command_ack_send(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )

    def _flush_texts(self) -> None:
        texts = self.firmware.texts
        while texts:
            severity, text = texts.pop(0)
            if not self._frozen and self._conn is not None:
                self._streams.text(self._conn.mav, severity, text)

    def _on_command(self, msg: Any) -> None:
        cmd = msg.command
        params = [
            msg.param1,
            msg.param2,
            msg.param3,
            msg.param4,
            msg.param5,
            msg.param6,
            msg.param7,
        ]
        if self._t < self.firmware.first_heartbeat_s:
            return  # not running yet: nothing answers
        with self._lock:
            if cmd == mp.CMD_SET_MESSAGE_INTERVAL:
                result = self._streams.set_interval(self._t, int(msg.param1), msg.param2)
            elif cmd == 11:  # ArduPilot's ack id of SET_MODE (see _SetModeCommand)
                result = self.firmware.command(self._t, mp.CMD_DO_SET_MODE, params)
            else:
                result = self.firmware.command(self._t, cmd, params)
        self._ack(msg, result)
        self._flush_texts()


class _SetModeCommand:
    """SET_MODE (#11, what MAVROS's ``set_mode`` service sends: mavros sys_status.cpp
    ``set_mode_cb``) as the DO_SET_MODE command the firmware makes of it. ArduPilot
    (``GCS_Common.cpp`` ``handle_set_mode``): custom_mode is the mode number, acked as
    COMMAND_ACK with command 11; PX4 (``mavlink_receiver.cpp`` ``handle_message_set_mode``):
    main mode in custom_mode bits 16-23, sub mode in 24-31, acked as DO_SET_MODE (176)."""

    def __init__(self, msg: Any, autopilot: str) -> None:
        cm = int(msg.custom_mode)
        if autopilot == "px4":
            self.command, main, sub = mp.CMD_DO_SET_MODE, (cm >> 16) & 0xFF, (cm >> 24) & 0xFF
        else:
            self.command, main, sub = 11, cm, 0
        self.param1, self.param2, self.param3 = float(msg.base_mode), float(main), float(sub)
        self.param4 = self.param5 = self.param6 = self.param7 = 0.0
        self._src = (msg.get_srcSystem(), msg.get_srcComponent())

    def get_srcSystem(self) -> int:  # noqa: N802 (pymavlink's name)
        return self._src[0]

    def get_srcComponent(self) -> int:  # noqa: N802
        return self._src[1]


# --------------------------------------------------------------------- process form (CLI)


def _floats(text: str, n: int, what: str, example: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise ConfigError(
            f"{what} must be {n} comma-separated finite numbers like {example}, got {text!r}"
        )
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
        raise ConfigError(
            f"--mavlink {url}: cannot listen there ({exc.strerror or exc}; another vehicle on this port?)"
        ) from None
    finally:
        probe.close()


def run_vehicle_cli(args: Any) -> int:
    """``openconvoy vehicle --sim``: run one simulated vehicle until SIGINT/SIGTERM.

    Prints one ready line to stdout. SIGUSR1: a person switches to MANUAL; SIGUSR2:
    toggle the telemetry freeze."""
    import signal

    from openconvoy.bridge.mavlink.link import check_url
    from openconvoy.envs.vehicles import vehicle_preset

    if not args.sim:
        raise ConfigError(
            "only simulated vehicles exist here: add --sim (a real vehicle runs its own autopilot)"
        )
    check_url(args.mavlink)
    _check_port_free(args.mavlink)
    x, y, heading = parse_start(args.start)
    config = SimVehicleConfig(
        system_id=args.id,
        autopilot=args.autopilot,
        preset=vehicle_preset(args.preset) if args.preset else None,
        home=parse_home(args.home),
        start_x_m=x,
        start_y_m=y,
        start_heading_rad=heading,
        timing=args.timing,
        ready_after_s=args.ready_after,
        rc_mode_switch=not args.no_rc_switch,
        setpoint_timeout_s=args.setpoint_timeout,
        max_message_hz=args.max_rate,
        speedup=args.speedup,
        boot_on_connect=args.boot_on_connect,
        gps_noise_m=args.gps_noise,
        seed=args.seed,
        hold_drift_mps=getattr(args, "hold_drift", 0.0),
        other_streams_hz=getattr(args, "other_streams", 0.0),
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
    motion = config.preset.name if config.preset else "firmware loops"
    print(
        f"vehicle {config.system_id}: simulated {config.autopilot} ({motion}, {config.timing} "
        f"timing) on {args.mavlink}, home {h.lat_deg:.7f},{h.lon_deg:.7f},{h.alt_m:g}, "
        f"arming possible after {config.armable_after_s:g} s",
        flush=True,
    )
    vehicle.run_forever()
    vehicle.stop()
    return 0
