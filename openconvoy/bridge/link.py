"""The vehicle link: what the real-time runner needs from an autopilot connection.

A small protocol so that the runner (``deploy``) does not care whether it talks MAVLink
through pymavlink (``bridge.mavlink.link.MavlinkLink``), MAVROS (ROS 1 or 2), PX4 or ArduPilot DDS. Everything here is
in the internal conventions (DESIGN.md): SI units, ENU around the convoy origin, heading
0 = east counter-clockwise in radians. MAVLink's NED and its integer encodings never leave
the implementation.

The runner calls ``poll`` and ``setpoints.send`` every control tick (20-50 Hz): both must be
non-blocking and fast. ``connect``, ``modes.prepare_and_arm``, ``modes.hold`` and ``reconnect``
may block for up to their timeout and are meant for start-up, stops and link recovery.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

from openconvoy.core.errors import LinkError
from openconvoy.core.state import VehicleState

Autopilot = Literal["ardupilot", "px4"]
"""Which firmware family a link talks to."""

StatusCallback = Callable[[str], None]
"""Receives one human-readable status line (waiting for arming, refused rates, ...)."""


class VehicleLinkError(LinkError, RuntimeError):
    """A link failure the runner cannot work around by waiting (base class)."""


class LinkTimeout(VehicleLinkError):
    """Nothing (or not the expected answer) arrived from the vehicle in time."""


class LinkLost(VehicleLinkError):
    """The connection is gone (TCP closed by the peer, serial device vanished)."""


class CommandRefused(VehicleLinkError):
    """The autopilot answered a command with a refusal.

    Attributes:
        command: the command's name, e.g. ``"MAV_CMD_COMPONENT_ARM_DISARM"``.
        result: the autopilot's result name, e.g. ``"MAV_RESULT_FAILED"``.
        reason: the autopilot's latest status text explaining it ("" if none arrived).
    """

    def __init__(self, command: str, result: str, reason: str = "") -> None:
        self.command = command
        self.result = result
        self.reason = reason
        why = f": {reason}" if reason else ""
        super().__init__(f"{command} refused by the autopilot ({result}){why}")


class ModeLost(VehicleLinkError):
    """The vehicle left the guided mode between arming and the first motion setpoint and
    did not keep it when asked again; the message names the mode and who set it."""


@dataclass(frozen=True, slots=True)
class Telemetry:
    """The latest picture of the vehicle, in internal units.

    Attributes:
        state: position (ENU, m), forward speed (m/s), heading (rad, 0 = east, CCW),
            acceleration (m/s², differentiated from speed), yaw rate (rad/s, CCW).
            ``state.t`` is the wall-clock time (s) the newest telemetry was measured
            (the vehicle's timestamp mapped onto the wall clock; ``wall - state.t`` is
            the state's age, including time spent in buffers).
        lat_deg, lon_deg: the vehicle's geodetic position, degrees.
        mode: the autopilot's mode name, e.g. ``"GUIDED"``, ``"HOLD"``, ``"OFFBOARD"``.
        armed: motors armed.
        t_telemetry: link clock (s) when the newest position message arrived (attitude
            alone does not count: a frozen position must look stale).
        t_heartbeat: link clock (s) when the newest vehicle heartbeat arrived.
        range_m: forward rangefinder reading (m, from the sensor — the front bumper — to
            the obstacle ahead), NaN when the vehicle has none or nothing is in range.
        range_rate_mps: its rate of change (m/s, negative = closing), NaN when unknown.
        t_range: link clock (s) when ``range_m`` arrived (-inf if never).
    """

    state: VehicleState
    lat_deg: float
    lon_deg: float
    mode: str
    armed: bool
    t_telemetry: float
    t_heartbeat: float
    range_m: float = math.nan
    range_rate_mps: float = math.nan
    t_range: float = -math.inf


@runtime_checkable
class Setpoints(Protocol):
    """Driving the vehicle: what the runner sends every control tick (non-blocking, fast)."""

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Command a forward speed (m/s) and an absolute ENU heading (rad); non-blocking.

        Returns False (and sends nothing) once a pilot took over, or when the link may
        not command the vehicle any more (PX4's offboard stream ended)."""
        ...

    def stop(self) -> bool:
        """Command speed 0 while keeping the current heading (never a zero velocity vector)."""
        ...


@runtime_checkable
class Modes(Protocol):
    """Arming, the hold mode, and who has the vehicle: the autopilot's modes as the runner
    uses them. The calls may block for up to their timeout (start-up, stops)."""

    @property
    def pilot_took_over(self) -> bool:
        """True (latched) once the mode left GUIDED/OFFBOARD without this link asking.

        The runner must then stop commanding and never switch back by itself."""
        ...

    @property
    def takeover_reason(self) -> str:
        """One line: which mode the vehicle went to and who set it ("" before a takeover)."""
        ...

    @property
    def failsafe_took_over(self) -> bool:
        """The takeover was the autopilot's own failsafe (not a person): a failed run."""
        ...

    def prepare_and_arm(self, timeout_s: float, on_status: StatusCallback | None = None) -> None:
        """Bring the vehicle into the externally guided mode and arm it, standing still.

        Waits (with status lines) while the autopilot refuses arming, up to ``timeout_s``;
        then raises ``CommandRefused`` naming the command and the autopilot's reason."""
        ...

    def hold(self, timeout_s: float = 2.0) -> None:
        """Switch the autopilot to its hold mode; 0 = do not wait. Stop first (PX4's Hold
        loops back to where it engaged, ArduPilot's coasts without braking)."""
        ...

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Disarm (standing still); 0 = send and do not wait."""
        ...


@runtime_checkable
class VehicleLink(Protocol):
    """What the runner uses to read and drive one vehicle: exactly that, no more (the
    runner reads nothing else of a link; ``tests/bridge/test_link_contract.py`` holds every
    link to it). The seam further links are written against.

    A link is the connection and its telemetry, plus two capability objects: ``setpoints``
    (driving, every tick) and ``modes`` (arming, hold, takeover). ``MavlinkLink`` hands out
    the parts that do the work (``mavlink.setpoint.SetpointStream``,
    ``mavlink.modes.ModeControl``); a link whose parts share one state (the ROS and DDS
    links, ``IdealLink``) implements a capability itself and names itself
    (``self.modes = self``).

    Attributes:
        telemetry_timeout_s: the runner's watchdog declares the link lost after this long
            without position telemetry (s).
        heartbeat_timeout_s: likewise without a vehicle heartbeat (s).
        telemetry_rates: message name -> rate (Hz) the vehicle agreed to (run metadata).
        setpoints: driving the vehicle (``Setpoints``).
        modes: arming, the hold mode and the latched takeover (``Modes``).
    """

    telemetry_timeout_s: float
    heartbeat_timeout_s: float
    telemetry_rates: dict[str, float]
    setpoints: Setpoints
    modes: Modes

    @property
    def autopilot(self) -> Autopilot:
        """``"ardupilot"`` or ``"px4"``; valid after ``connect``."""
        ...

    @property
    def lost(self) -> bool:
        """No usable connection (closed by the peer, device gone): ``reconnect`` it."""
        ...

    def connect(self, timeout_s: float) -> None:
        """Open the link, wait for the vehicle's heartbeat, identify it, request telemetry.

        Raises ``LinkTimeout`` when no heartbeat arrives within ``timeout_s`` seconds."""
        ...

    def poll(self) -> Telemetry | None:
        """Handle every message pending (non-blocking); the new telemetry, or None if none."""
        ...

    def reconnect(self, timeout_s: float) -> None:
        """Close and reopen the link, then wait for a heartbeat and re-request telemetry;
        ``timeout_s`` = 0 starts that and returns at once (``poll`` finishes it)."""
        ...

    def close(self) -> None:
        """Release the connection (idempotent)."""
        ...
