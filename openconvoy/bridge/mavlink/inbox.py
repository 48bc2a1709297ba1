"""What ``MavlinkLink`` does with each message it receives, and how many came of each type.

Heartbeats identify the vehicle and report its mode (a mode change this link did not ask
for is a takeover); positions, attitudes and ranges become ``Telemetry``; status texts and
command answers are kept for the commands waiting on them. Only the identified vehicle's
messages count: other systems on the same link (another GCS, other vehicles on a shared
radio) are ignored.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from openconvoy.bridge.link import CommandRefused, StatusCallback, Telemetry
from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.command import Commander
from openconvoy.bridge.mavlink.modes import ModeControl
from openconvoy.bridge.mavlink.ranging import RangeIntake
from openconvoy.bridge.mavlink.setpoint import SetpointStream
from openconvoy.bridge.mavlink.telemetry import TelemetryIntake
from openconvoy.bridge.mavlink.watch import VehicleWatch
from openconvoy.comms.geodesy import Origin


class Inbox:
    """Routes received messages and counts them.

    Args:
        clocks: (monotonic link clock, wall clock), s.
        origin: the convoy origin (ENU frame).
        vehicle: (vehicle id, length m, width m) written into the telemetry's state.
        heartbeat_timeout_s: a heartbeat after a longer silence re-requests telemetry.
        parts: the link's vehicle watch, mode control, setpoint stream and commander.
        rates: the accepted telemetry rates (re-sent to a vehicle back after silence).
        status: status line callback.

    Attributes:
        counts: messages received from the vehicle per type.
        last_refusal: the newest refused command (from any COMMAND_ACK).
        telemetry: the newest telemetry built.
    """

    def __init__(
        self,
        clocks: tuple[Callable[[], float], Callable[[], float]],
        origin: Origin,
        vehicle: tuple[int, float, float],
        heartbeat_timeout_s: float,
        parts: tuple[VehicleWatch, ModeControl, SetpointStream, Commander],
        rates: Callable[[], dict[str, float]],
        status: StatusCallback,
    ) -> None:
        self._clock, self._wall = clocks
        self._origin = origin
        self._vehicle = vehicle
        self._heartbeat_timeout_s = heartbeat_timeout_s
        self._watch, self._modes, self._stream, self._cmd = parts
        self._rates = rates
        self._status = status
        self.counts: dict[str, int] = {}
        self.last_refusal: CommandRefused | None = None
        self.reset()

    def reset(self) -> None:
        """A new connection: forget the telemetry and the ranges (counts stay)."""
        self.intake = TelemetryIntake(self._origin, self._clock, self._wall, self._on_reboot)
        self.ranging = RangeIntake()
        self.telemetry: Telemetry | None = None

    def take_telemetry(self) -> Telemetry | None:
        """New telemetry since the last call (a position is known), else None."""
        if not self.intake.take():
            return None
        w = self._watch
        self.telemetry = self.intake.build(
            self._vehicle, w.mode, w.armed, w.t_heartbeat, self.ranging
        )
        return self.telemetry

    def _count(self, kind: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def handle(self, msg: Any) -> None:
        """One message from the connection, to whom it concerns."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg)
            return
        target = self._watch.target
        if target is None or msg.get_srcSystem() != target[0]:
            return  # other systems (another GCS, other vehicles on a shared radio)
        self._count(kind)
        if kind == "GLOBAL_POSITION_INT":
            self.intake.on_position(msg)
        elif kind == "ATTITUDE":
            self.intake.on_attitude(msg)
        elif kind == "DISTANCE_SENSOR":
            self.ranging.on_distance(msg, self._clock())
        elif kind == "STATUSTEXT":
            self._watch.on_text(msg)
        elif kind == "COMMAND_ACK" and self._watch.on_ack(msg):
            self.last_refusal = CommandRefused(
                mp.command_name(msg.command), mp.result_name(msg.result), self._watch.reason()
            )

    def _on_heartbeat(self, msg: Any) -> None:
        w = self._watch
        if not w.is_autopilot_heartbeat(msg):
            return
        self._count("HEARTBEAT")
        w.heartbeats += 1
        w.autopilot_id = msg.autopilot
        now = self._clock()
        if now - w.t_heartbeat > self._heartbeat_timeout_s and self._rates():
            # The vehicle is back after silence (maybe rebooted, forgetting our intervals).
            self._cmd.resend_intervals(self._rates(), self._status)
        w.t_heartbeat = now
        w.armed = bool(msg.base_mode & mp.mav().MAV_MODE_FLAG_SAFETY_ARMED)
        w.system_status = int(msg.system_status)
        mode = mp.mode_name(msg.autopilot, msg.custom_mode)
        if self._modes.observe_mode(mode):
            self._stream.end("a mode change we did not ask for")
            reason = self._modes.takeover_reason
            self._status(f"{reason}: somebody else took over; no more setpoints")
        w.mode = mode

    def _on_reboot(self) -> None:
        """The vehicle's clock went back: it rebooted and forgot the intervals."""
        if self._rates():
            self._cmd.resend_intervals(self._rates(), self._status)
