"""Setpoint encoding per autopilot for ``MavlinkLink`` (see ``bridge.mavlink.link``'s docstring
for what each firmware does with a SET_POSITION_TARGET_*; checked in their sources and
recordings).

ArduPilot: type_mask 2503, vx = the speed along the body axis (negative = reverse), vy =
0, yaw absolute. PX4: the NED vector of the speed along the heading (PX4 rovers cannot
reverse: a negative speed is sent as a stop), never shorter than ``PX4_STOP_MPS`` so that
it keeps a bearing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from openconvoy.bridge.link import Autopilot, StatusCallback
from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.connection import MavConnection
from openconvoy.bridge.mavlink.modes import ModeControl
from openconvoy.bridge.mavlink.watch import VehicleWatch
from openconvoy.core.state import wrap_angle

PX4_STOP_MPS = 0.001  # PX4's stop: a vanishing vector that still has a bearing
PX4_RESUME_GAP_S = 1.0  # COM_OF_LOSS_T: after such a pause PX4 may be in its failsafe


@dataclass(frozen=True, slots=True)
class Setpoint:
    """One encoded setpoint.

    Attributes:
        vx, vy: the message's NED velocity fields (m/s).
        yaw: the message's NED yaw (rad).
        speed: the speed it commands (m/s; PX4 never below 0), as logged.
    """

    vx: float
    vy: float
    yaw: float
    speed: float


def encode_setpoint(autopilot: Autopilot, speed_mps: float, heading_rad: float) -> Setpoint:
    """The message fields for a forward speed (m/s; non-finite = 0) and an ENU heading
    (rad) on ``autopilot``."""
    speed = float(speed_mps)
    if not math.isfinite(speed):
        speed = 0.0
    yaw = wrap_angle(math.pi / 2 - float(heading_rad))  # ENU heading -> NED yaw
    if autopilot == "px4":
        along = max(speed, PX4_STOP_MPS)
        return Setpoint(along * math.cos(yaw), along * math.sin(yaw), yaw, max(speed, 0.0))
    # + 0.0 turns a -0.0 into +0.0: only v < 0 reverses
    return Setpoint(speed + 0.0, 0.0, yaw, speed)


def send_setpoint_message(
    mav: Any,
    frame: Literal["global", "local"],
    t_ms: int,
    target: tuple[int, int],
    sp: Setpoint,
) -> None:
    """SET_POSITION_TARGET_GLOBAL_INT (``"global"``) or _LOCAL_NED (``"local"``) with
    type_mask 2503 (velocity + yaw) through pymavlink's ``mav``; positions unused (0)."""
    if frame == "global":
        send = mav.set_position_target_global_int_send
        head: tuple[Any, ...] = (
            mp.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            mp.TYPE_MASK_VEL_YAW,
            0,
            0,
            0.0,
        )
    else:  # lat_int and lon_int above are integers on the wire, x and y here floats
        send = mav.set_position_target_local_ned_send
        head = (mp.MAV_FRAME_LOCAL_NED, mp.TYPE_MASK_VEL_YAW, 0.0, 0.0, 0.0)
    ts, tc = target
    send(t_ms, ts, tc, *head, sp.vx, sp.vy, 0.0, 0.0, 0.0, 0.0, sp.yaw, 0.0)


class SetpointStream:
    """The setpoints to one vehicle: encoded for its autopilot, sent without waiting, and
    ended for good on PX4 once it may be in its offboard-loss failsafe.

    PX4's commander leaves OFFBOARD ``COM_OF_LOSS_T`` (1 s) after the last setpoint and
    returns to OFFBOARD by itself when setpoints resume: once the stream paused that long,
    the autopilot link was lost, or a mode change this link did not ask for was seen, no
    setpoint goes out again (``ended``). ``MavlinkLink.setpoints``, the link's
    ``bridge.link.Setpoints``; ``heading`` gives the vehicle's current heading (rad, ENU;
    None before telemetry) that ``stop`` holds.

    Attributes:
        ended: why no more setpoints go out ("" while they may).
        last: (speed m/s, heading rad, clock s) of the newest setpoint sent.
        t0: clock (s) the message's ``time_boot_ms`` counts from.
        frame: ``"auto"`` (ArduPilot GLOBAL_INT, PX4 LOCAL_NED), ``"global"`` or ``"local"``.
    """

    def __init__(
        self,
        clock: Callable[[], float],
        link: MavConnection,
        watch: VehicleWatch,
        modes: ModeControl,
        link_ok: Callable[[float], bool],
        status: StatusCallback,
        frame: Literal["auto", "global", "local"] = "auto",
        heading: Callable[[], float | None] = lambda: None,
    ) -> None:
        self._clock = clock
        self._link = link
        self._watch = watch
        self._modes = modes
        self._link_ok = link_ok
        self._status = status
        self._heading = heading
        self.frame = frame
        self.ended = ""
        self.last: tuple[float, float, float] | None = None
        self.t0 = clock()

    def end(self, why: str) -> None:
        """End the stream (latched; PX4 only: ArduPilot never re-engages by itself)."""
        if not self.ended and self._watch.autopilot_id == mp.AUTOPILOT_PX4:
            self.ended = why

    def _frame(self) -> Literal["global", "local"]:
        if self.frame != "auto":
            return self.frame
        return "local" if self._watch.autopilot() == "px4" else "global"

    def _may_send(self, now: float) -> bool:
        """Whether a setpoint may go out now; ends the stream on PX4 once it paused longer
        than ``COM_OF_LOSS_T`` or the autopilot link was lost while engaged (PX4 would be in
        its failsafe and would take OFFBOARD back on the next setpoint: a run must not
        resume driving a vehicle whose failsafe took it)."""
        if (
            self._link.conn is None
            or self._watch.target is None
            or self._modes.pilot_took_over
            or self.ended
        ):
            return False
        if self._watch.autopilot() == "px4" and self._modes.engaged_mode is not None:
            gap = now - self.last[2] if self.last is not None else 0.0
            if gap > PX4_RESUME_GAP_S:
                self.end(f"the setpoint stream paused {gap:.2f} s (PX4's COM_OF_LOSS_T is 1 s)")
            elif not self._link_ok(now):
                self.end("the autopilot link was lost")
            if self.ended:
                self._status(f"no more setpoints to this PX4: {self.ended}")
                return False
        return True

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Send speed (m/s, forward) and ENU heading (rad); one MAVLink message, no waiting.

        Encoded per autopilot by ``encode_setpoint`` (see ``mavlink.link``'s docstring).
        Returns False without sending when there is no link, a pilot took over, or the
        PX4 stream ended (``ended``)."""
        now = self._clock()
        if not self._may_send(now):
            return False
        target = self._watch.target
        assert target is not None  # _may_send checked it
        sp = encode_setpoint(self._watch.autopilot(), speed_mps, heading_rad)
        t_ms = int((now - self.t0) * 1000) & 0xFFFFFFFF
        send_setpoint_message(self._link.conn.mav, self._frame(), t_ms, target, sp)
        self.last = (sp.speed, float(heading_rad), now)
        return True

    def stop(self) -> bool:
        """Speed 0 along the current heading (before telemetry: the last commanded one,
        else east): ArduPilot vx = 0 with yaw = heading; PX4 a 0.001 m/s vector along it.

        Never the zero velocity vector, which both firmwares read as "bearing north"."""
        heading_rad = self._heading()
        if heading_rad is None:
            heading_rad = self.last[1] if self.last else 0.0
        return self.send(0.0, heading_rad)
