"""``MavlinkLink``: the vehicle link over MAVLink (pymavlink), for ArduPilot Rover and PX4.

Follows shared/AUTOPILOTS.md and the firmware recordings in shared/sitl/ (ArduPilot Rover
4.7) and shared/sitl-px4/ (PX4 main, SIH Ackermann rover):

- connect by URL (``/dev/ttyUSB0`` with ``baud``, ``udp:``/``udpin:`` listen, ``udpout:``
  send, ``tcp:`` connect, ``tcpin:`` listen), wait for a vehicle heartbeat, identify the
  firmware (autopilot 3 = ArduPilot, 12 = PX4);
- telemetry is requested per message with ``MAV_CMD_SET_MESSAGE_INTERVAL`` at
  ``telemetry_hz`` (independent of the control rate); a refused rate is reported and
  retried lower. Only GLOBAL_POSITION_INT keeps the telemetry fresh (``link_ok``,
  ``Telemetry.t_telemetry``): ATTITUDE alone must not let a vehicle drive on a frozen
  position;
- a forward rangefinder (DISTANCE_SENSOR with orientation 0) gives range and range rate;
- arming: GUIDED / OFFBOARD (confirmed by the heartbeat), then arm, retrying while the
  autopilot refuses with its status text, bounded by a timeout; then the mode is checked
  again on a heartbeat received after arming (ArduPilot's RC mode switch sets MANUAL
  ~0.4 s after "ArduPilot Ready", and arming is accepted in MANUAL): a changed mode is
  requested again a bounded number of times, else the vehicle is disarmed and ``ModeLost``
  names the mode and who set it;
- every command's COMMAND_ACK is checked; a refusal raises ``CommandRefused`` with the
  autopilot's latest STATUSTEXT;
- a GCS heartbeat goes out at 1 Hz; lost links are detected (silence, missing heartbeat,
  TCP EOF — pymavlink reports that in a busy loop instead of raising); ``reconnect(0)``
  reopens in a helper thread and never blocks the caller;
- a mode change away from GUIDED/OFFBOARD that this link did not ask for latches
  ``modes.pilot_took_over`` (``takeover_reason`` says by whom, as far as the link can tell).

Setpoints: what each firmware does with them (checked in its source and its recordings)
---------------------------------------------------------------------------------------

ArduPilot Rover, ``Rover/GCS_MAVLink_Rover.cpp`` (``handle_set_position_target_global_int``
and ``_local_ned``, unchanged since 2017): with the yaw or yaw-rate field in use, the sign of
``vx`` alone selects the direction ("we are using the x-axis velocity to determine
direction even though the frame is provided in MAV_FRAME_GLOBAL_xxx": ``if
(is_negative(packet.vx)) speed_dir = -1``), the speed is |(vx, vy)| and the nose points at
``yaw``. A NED vector with yaw therefore reverses on every heading with a southward
component (recorded: shared/sitl/ rows 6-8). So we send type_mask 2503, ``vx`` = the
body-forward speed, ``vy`` = 0, ``yaw`` absolute; only a negative commanded speed reverses.
Stop = speed 0 with yaw = the current heading (row 20: heading held within 0.5°), never the
zero velocity-only setpoint (row 21: "heading north", the nose swings ~80°). GLOBAL_INT is
used because LOCAL_NED is ignored until the EKF has an origin (rows 24-25).

PX4, ``src/modules/mavlink/mavlink_receiver.cpp`` (``handle_message_set_position_target_
local_ned`` / ``_global_int``): the message's velocity becomes ``trajectory_setpoint.velocity``
and ``offboard_control_mode.velocity``; the yaw is copied but the rover modules do not use it.
``src/modules/rover_ackermann/AckermannDriveModes/AckermannOffboardMode/AckermannOffboardMode.cpp``
(``offboardControl``): ``speed_body_x = |(vx, vy)|`` and ``yaw_setpoint = atan2f(vy, vx)``, so
the rover steers to the vector's bearing, never reverses, ignores the yaw field, and a zero
vector means bearing atan2(±0, ±0) = north or south by the sign of the zero (recorded:
shared/sitl-px4/ rows 7-9, 20-21: a ~48° swing from 2 m/s). ``rover_differential`` and
``rover_mecanum`` have their own offboard modes. So we keep the NED vector (speed along the
heading; type_mask 2503 with the yaw for firmwares that use it), and stop with a vanishing
vector along the current bearing (``mavlink.setpoint.PX4_STOP_MPS`` = 0.001 m/s; recorded: stopped in
1.25 s from 2 m/s, heading 90.4 → 90.0°). PX4's commander leaves OFFBOARD
``COM_OF_LOSS_T`` (1 s) after the last setpoint and **returns to OFFBOARD by itself when
setpoints resume** (recorded, rows 16-18), so once the stream has paused that long, or the
autopilot link was lost, or a mode change we did not ask for was seen, this link sends no
setpoint again (``setpoints.ended``) until a new run.

Not thread-safe: one thread (the runner's loop) owns a link.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Literal

from openconvoy.bridge.link import Autopilot, LinkTimeout, StatusCallback, Telemetry
from openconvoy.bridge.mavlink.command import Commander
from openconvoy.bridge.mavlink.connection import MavConnection
from openconvoy.bridge.mavlink.inbox import Inbox
from openconvoy.bridge.mavlink.modes import ModeControl
from openconvoy.bridge.mavlink.setpoint import SetpointStream
from openconvoy.bridge.mavlink.watch import VehicleWatch
from openconvoy.comms.geodesy import Origin
from openconvoy.core.errors import ConfigError

log = logging.getLogger(__name__)

_URL_SCHEMES = ("udp:", "udpin:", "udpout:", "tcp:", "tcpin:")


def check_url(url: str) -> str:
    """Validate a link URL; returns it. Raises ValueError naming what is wrong."""
    if url.startswith(_URL_SCHEMES):
        rest = url.split(":", 1)[1]
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ConfigError(
                f"MAVLink URL {url!r}: expected SCHEME:HOST:PORT with PORT in 1..65535, e.g. udpin:0.0.0.0:14550"
            )
        return url
    if url.startswith("/dev/") or url.upper().startswith("COM"):
        return url
    raise ConfigError(
        f"MAVLink URL {url!r}: expected a serial device (/dev/ttyX) or one of "
        f"{', '.join(s + 'HOST:PORT' for s in _URL_SCHEMES)}"
    )


class MavlinkLink:
    """A ``VehicleLink`` to one ArduPilot Rover or PX4 vehicle over pymavlink.

    The link owns the connection (open, reopen, the GCS heartbeat, draining messages) and
    hands out the parts that do the rest, so that a caller talks to the part it means:

    - ``setpoints`` (``mavlink.setpoint.SetpointStream``): ``send``, ``stop``; and what
      went out (``last``, ``ended``, ``frame``);
    - ``modes`` (``mavlink.modes.ModeControl``): ``prepare_and_arm``, ``hold``,
      ``disarm``, ``set_mode``; the latched takeover (``pilot_took_over``,
      ``takeover_reason``, ``failsafe_took_over``);
    - ``watch`` (``mavlink.watch.VehicleWatch``): what the heartbeats and status texts
      say (``mode``, ``armed``, ``system_id``, ``status_texts``);
    - ``inbox`` (``mavlink.inbox.Inbox``): what arrived (``telemetry``, ``last_refusal``,
      ``counts`` per message type).

    Args:
        url: connection URL (see module docstring); serial devices use ``baud``.
        origin: convoy origin; positions are ENU metres around it.
        baud: serial baud rate (ignored for network URLs).
        vehicle_id: convoy position written into ``VehicleState.vehicle_id``.
        telemetry_hz: requested rate of GLOBAL_POSITION_INT and ATTITUDE, Hz.
        telemetry_timeout_s: ``link_ok`` is False after this long without telemetry, s.
        heartbeat_timeout_s: ``link_ok`` is False after this long without a heartbeat, s.
        length_m, width_m: vehicle size copied into the state (0 = unknown).
        setpoint_frame: ``"auto"`` (ArduPilot GLOBAL_INT, PX4 LOCAL_NED), ``"global"`` or
            ``"local"``.
        source_system, source_component: our MAVLink ids (default: a GCS-class system id
            and MAV_COMP_ID_ONBOARD_COMPUTER).
        clock: monotonic clock (s) for timeouts and freshness.
        wall_clock: clock (s) stamped into ``VehicleState.t`` (the shared, disciplined clock).
        on_status: receives status lines (refused rates, waiting for arming); default logs.
    """

    def __init__(
        self,
        url: str,
        origin: Origin,
        baud: int = 57600,
        *,
        vehicle_id: int = 0,
        telemetry_hz: float = 20.0,
        telemetry_timeout_s: float = 0.5,
        heartbeat_timeout_s: float = 3.0,
        length_m: float = 0.0,
        width_m: float = 0.0,
        setpoint_frame: Literal["auto", "global", "local"] = "auto",
        source_system: int = 255,
        source_component: int = 191,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        on_status: StatusCallback | None = None,
    ) -> None:
        self.url = check_url(url)
        if telemetry_hz <= 0:
            raise ConfigError(f"telemetry_hz must be positive, got {telemetry_hz}")
        self.origin = origin
        self.baud = baud
        self.vehicle_id = vehicle_id
        self.telemetry_hz = float(telemetry_hz)
        self.telemetry_timeout_s = telemetry_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.length_m = length_m
        self.width_m = width_m
        self.source_system = source_system
        self.source_component = source_component
        self._clock = clock
        status = on_status or (lambda line: log.warning("%s", line))
        self._status = status
        self._link = MavConnection(url, baud, source_system, source_component, status)
        self.watch = VehicleWatch(clock)
        self._cmd = Commander(clock, self._link, self.watch, self._service)
        self.modes = ModeControl(clock, self._link, self.watch, self._cmd, status)
        self.setpoints = SetpointStream(
            clock,
            self._link,
            self.watch,
            self.modes,
            self.link_ok,
            status,
            setpoint_frame,
            heading=lambda: self.inbox.intake.heading,
        )
        self.telemetry_rates: dict[str, float] = {}
        """Accepted telemetry rate per message name, Hz (after ``connect``)."""
        parts = (self.watch, self.modes, self.setpoints, self._cmd)
        vehicle = (vehicle_id, length_m, width_m)
        self.inbox = Inbox(
            (clock, wall_clock),
            origin,
            vehicle,
            heartbeat_timeout_s,
            parts,
            lambda: self.telemetry_rates,
            status,
        )
        self._reset_link_state()

    def _reset_link_state(self) -> None:
        """A new connection: forget the vehicle, its telemetry and ranges."""
        self._link.reset()
        self.watch.reset()
        self.modes.reset_keepalive()
        self.inbox.reset()
        self.setpoints.t0 = self._clock()

    def connect(self, timeout_s: float = 10.0) -> None:
        """Open the link, wait for a vehicle heartbeat, identify it and request telemetry.

        Raises ``LinkTimeout`` (no heartbeat within ``timeout_s`` s), ``LinkLost`` (cannot
        open), ``CommandRefused`` (no telemetry rate, down to 1 Hz, accepted)."""
        link = self._link
        if link.conn is None:
            self._reset_link_state()
            link.open()
        found = lambda: self.watch.target is not None  # noqa: E731
        quiet = min(3.0, timeout_s)  # a vehicle that answers at once needs no word
        if not self._cmd.wait_until(found, quiet) and timeout_s > quiet:
            self._status(
                f"no heartbeat on {self.url} yet: waiting up to {timeout_s - quiet:g} s more "
                "for the vehicle (is it powered, and the URL its telemetry port?)"
            )
        if not found() and not (
            timeout_s > quiet and self._cmd.wait_until(found, timeout_s - quiet)
        ):
            raise LinkTimeout(
                f"no heartbeat from a vehicle on {self.url} within {timeout_s:g} s"
                + (f" ({link.lost_reason})" if link.eof else "")
            )
        self.telemetry_rates = self._cmd.request_intervals(self.telemetry_hz, self._status)

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen a lost connection (``lost``: TCP EOF/reset, device error, or a failed
        reopen), wait for a heartbeat and re-request telemetry. A connection that is open
        but still waiting for its first heartbeat is kept, so repeated short calls add up.
        Raises like ``connect``. ``modes.pilot_took_over`` stays latched.

        ``timeout_s`` <= 0 never blocks (what the runner's loop calls): the connection is
        opened in a helper thread (a TCP connect can take seconds) and installed by a later
        ``poll``; the telemetry intervals are re-sent without waiting for their ACKs when
        the first heartbeat arrives, so a vehicle that answers heartbeats but not commands
        cannot stall the caller. Open failures come as status lines."""
        if timeout_s > 0:
            if self.lost:
                self.close()
            self.connect(timeout_s)
            return
        if not self.lost or self._link.reopening:
            return
        self.close()
        self._reset_link_state()
        self._link.reopen_in_background()

    def close(self) -> None:
        """Close the connection (idempotent)."""
        self._link.close()

    @property
    def autopilot(self) -> Autopilot:
        """``"ardupilot"`` or ``"px4"``; raises if no heartbeat identified the vehicle yet."""
        return self.watch.autopilot()

    @property
    def lost(self) -> bool:
        """No usable connection (TCP EOF/reset, device error, never opened or reopening
        failed): call ``reconnect``. A silent UDP link is not ``lost``: see ``link_ok``."""
        return self._link.lost

    def link_ok(self, now: float) -> bool:
        """True while open, telemetry younger than ``telemetry_timeout_s`` and the heartbeat
        younger than ``heartbeat_timeout_s`` at link-clock time ``now`` (s)."""
        return (
            not self._link.lost
            and now - self.inbox.intake.t_telemetry <= self.telemetry_timeout_s
            and now - self.watch.t_heartbeat <= self.heartbeat_timeout_s
        )

    def poll(self) -> Telemetry | None:
        """Handle all pending messages and send the 1 Hz GCS heartbeat; non-blocking.

        Returns the new telemetry when a position or attitude message arrived since the
        last call (and a position is known), else None."""
        self._service()
        return self.inbox.take_telemetry()

    def _service(self) -> None:
        """Periodic sends (GCS heartbeat, PX4 keep-alive stream) and draining."""
        link = self._link
        link.install_pending()
        if link.conn is None:
            return
        now = self._clock()
        link.send_gcs_heartbeat(now)
        if self.modes.keepalive_due(now):
            self.setpoints.stop()
        link.drain(self.inbox.handle)
