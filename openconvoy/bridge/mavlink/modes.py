"""Arming and mode management for ``MavlinkLink`` (shared/AUTOPILOTS.md).

GUIDED (ArduPilot) or OFFBOARD (PX4), confirmed by the heartbeat, then arm, retrying while
the autopilot refuses with its status text, bounded by a timeout; then the mode is checked
again on a heartbeat received after arming (ArduPilot's RC mode switch sets MANUAL ~0.4 s
after "ArduPilot Ready", and arming is accepted in MANUAL): a changed mode is requested
again a bounded number of times, else the vehicle is disarmed and ``ModeLost`` names the
mode and who set it. A mode change away from the engaged mode that this link did not ask
for latches the takeover.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from openconvoy.bridge.link import (
    CommandRefused,
    LinkTimeout,
    ModeLost,
    StatusCallback,
    VehicleLinkError,
)
from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.command import Commander
from openconvoy.bridge.mavlink.connection import MavConnection
from openconvoy.bridge.mavlink.watch import VehicleWatch

PX4_PRESTREAM_S = 1.2  # PX4 v1.16+ wants > 1 s of setpoints above 2 Hz before OFFBOARD
MODE_CONFIRM_S = 2.5  # heartbeats come at 1 Hz: allow two and a half periods
RETRY_PAUSE_S = 1.0
MODE_REREQUESTS = 2  # a mode lost after arming is requested again this many times
KEEPALIVE_PERIOD_S = 0.1  # setpoint stream while blocking in PX4 preparation (10 Hz)


class ModeControl:
    """Requests modes and arming, and tells a takeover from a mode this link asked for:
    ``MavlinkLink.modes``, the link's ``bridge.link.Modes``.

    Attributes:
        engaged_mode: the guided mode once armed in it (None otherwise).
        requested_mode: the mode this link asked for last.
        pilot_took_over, takeover_reason, failsafe_took_over: the latched takeover.
        keepalive: the link's service loop streams stop setpoints (PX4 preparation).
    """

    def __init__(
        self,
        clock: Callable[[], float],
        link: MavConnection,
        watch: VehicleWatch,
        commander: Commander,
        status: StatusCallback,
    ) -> None:
        self._clock = clock
        self._link = link
        self._watch = watch
        self._cmd = commander
        self._status = status
        self.engaged_mode: str | None = None
        self.requested_mode: str | None = None
        self.pilot_took_over = False
        self.takeover_reason = ""
        self.failsafe_took_over = False
        self.reset_keepalive()

    def reset_keepalive(self) -> None:
        """No keep-alive stream (a new connection)."""
        self.keepalive = False
        self._t_keepalive = -math.inf

    def keepalive_due(self, now: float) -> bool:
        """Whether a keep-alive stop setpoint is due at clock ``now`` (s; at 10 Hz)."""
        if self.keepalive and now - self._t_keepalive >= KEEPALIVE_PERIOD_S:
            self._t_keepalive = now
            return True
        return False

    def _px4(self) -> bool:
        return self._watch.autopilot() == "px4"

    def guided_mode(self) -> str:
        return "OFFBOARD" if self._px4() else "GUIDED"

    def hold_mode(self) -> str:
        return "LOITER" if self._px4() else "HOLD"

    def mode_params(self, mode: str) -> tuple[float, ...]:
        """DO_SET_MODE parameters for a mode name."""
        flag = float(mp.mav().MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
        if self._px4():
            main, sub = mp.PX4_MODE_NUMBERS[mode]
            return (flag, float(main), float(sub))
        return (flag, float(mp.ROVER_MODE_NUMBERS[mode]))

    def observe_mode(self, mode: str) -> bool:
        """A heartbeat's mode: True (once, latched) when it leaves the engaged mode
        without this link asking."""
        if (
            self.engaged_mode is None
            or mode == self.engaged_mode
            or mode == self.requested_mode
            or self.pilot_took_over
        ):
            return False
        self.pilot_took_over = True
        who = self._watch.who_set_mode()
        self.failsafe_took_over = who.startswith("the autopilot's failsafe")
        self.takeover_reason = f"mode changed from {self.engaged_mode} to {mode}, set by {who}"
        return True

    def _retry_or_raise(
        self,
        what: str,
        refused: tuple[int, str],
        deadline: float,
        line: str,
        on_status: StatusCallback,
    ) -> None:
        """After a refusal (result, reason): raise ``CommandRefused`` past ``deadline``,
        else say ``line`` (its ``{result}`` and ``{reason}`` filled in) and pause before
        the next try."""
        result, reason = refused
        left = deadline - self._clock()
        if left <= 0:
            raise CommandRefused(what, mp.result_name(result), reason)
        said = line.format(result=mp.result_name(result), reason=reason or "no reason given")
        on_status(f"{said}; retrying for {left:.0f} s more")
        self._cmd.wait_until(lambda: False, min(RETRY_PAUSE_S, left))

    def request(self, mode: str, deadline: float, on_status: StatusCallback) -> None:
        """Request ``mode`` until the heartbeat shows it; retry refusals until ``deadline``."""
        self.requested_mode = mode
        watch = self._watch
        while True:
            result, reason = self._cmd.command(mp.CMD_DO_SET_MODE, self.mode_params(mode))
            if result == mp.RESULT_ACCEPTED:
                wait = max(0.0, min(MODE_CONFIRM_S, deadline - self._clock()))
                if self._cmd.wait_until(lambda: watch.mode == mode, wait):
                    return
                reason = reason or f"heartbeat still shows {watch.mode}"
            self._retry_or_raise(
                f"MAV_CMD_DO_SET_MODE({mode})",
                (result, reason),
                deadline,
                mode + " refused ({result}: {reason})",
                on_status,
            )

    def arm(self, deadline: float, on_status: StatusCallback, mode: str | None = None) -> None:
        """Arm, waiting out the autopilot's refusals (estimator not ready) until ``deadline``.

        Before every attempt the mode must still be ``mode``: ArduPilot's init and RC mode
        switch replace a GUIDED set early in boot by MANUAL (shared/sitl rows 3-4), and it
        accepts arming in MANUAL ~19 s before GUIDED is armable (row 2)."""
        watch = self._watch
        while True:
            if mode is not None and watch.mode != mode:
                on_status(
                    f"mode is {watch.mode} (set by {watch.who_set_mode()}), not {mode}: "
                    f"requesting {mode} again before arming"
                )
                self.request(mode, deadline, on_status)
            result, reason = self._cmd.command(mp.CMD_COMPONENT_ARM_DISARM, (1.0,))
            if result == mp.RESULT_ACCEPTED:
                wait = max(0.0, min(MODE_CONFIRM_S, deadline - self._clock()))
                if self._cmd.wait_until(lambda: watch.armed, wait):
                    return
                reason = reason or "heartbeat does not show armed"
            self._retry_or_raise(
                "MAV_CMD_COMPONENT_ARM_DISARM",
                (result, reason),
                deadline,
                "waiting to arm: {result}: {reason}",
                on_status,
            )

    def prepare_and_arm(
        self, timeout_s: float = 60.0, on_status: StatusCallback | None = None
    ) -> None:
        """Switch to GUIDED (ArduPilot) or OFFBOARD (PX4) and arm, standing still; then
        check the mode again on a heartbeat received after arming.

        PX4: streams stop setpoints (10 Hz) for 1.2 s first and during the whole call; from
        its return on, the caller must keep sending setpoints above 2 Hz. Refusals are
        retried with status lines (``on_status``) until ``timeout_s`` s have passed; then
        ``CommandRefused`` names the command and the autopilot's reason. A mode lost after
        arming (ArduPilot's RC mode switch at boot) is requested again up to
        ``MODE_REREQUESTS`` times; if it still does not hold, the vehicle is disarmed and
        ``ModeLost`` says which mode it is in and who set it. Not allowed once a pilot took
        over."""
        if self.pilot_took_over:
            raise CommandRefused(
                "prepare_and_arm", "PILOT_TOOK_OVER", "a pilot took over this vehicle"
            )
        status = on_status or self._status
        deadline = self._clock() + timeout_s
        target = self.guided_mode()
        self.engaged_mode = None
        if self._px4():
            self.keepalive = True
            try:
                self._cmd.wait_until(lambda: False, PX4_PRESTREAM_S)
                self.request(target, deadline, status)
                self.arm(deadline, status, target)
                self._keep_mode_after_arming(target, status)
            finally:
                self.keepalive = False
        else:
            self.request(target, deadline, status)
            self.arm(deadline, status, target)
            self._keep_mode_after_arming(target, status)
        self.engaged_mode = target
        self.requested_mode = target

    def _next_heartbeat(self) -> bool:
        """Wait for a heartbeat received after now (at most ``MODE_CONFIRM_S``)."""
        watch = self._watch
        n = watch.heartbeats
        return self._cmd.wait_until(lambda: watch.heartbeats > n, MODE_CONFIRM_S)

    def _keep_mode_after_arming(self, target: str, status: StatusCallback) -> None:
        """The mode on a heartbeat after arming must still be ``target``; else ask again
        (bounded), else disarm and raise ``ModeLost``."""
        watch = self._watch
        for attempt in range(MODE_REREQUESTS + 1):
            if not self._next_heartbeat():
                raise LinkTimeout(f"no heartbeat within {MODE_CONFIRM_S:g} s after arming")
            if watch.mode == target and watch.armed:
                return
            if not watch.armed:
                raise ModeLost(
                    f"vehicle disarmed right after arming (mode {watch.mode}, "
                    f"set by {watch.who_set_mode()})"
                )
            who = watch.who_set_mode()
            if attempt == MODE_REREQUESTS:
                break
            status(
                f"mode changed to {watch.mode} after arming, set by {who}; "
                f"requesting {target} again ({attempt + 1} of {MODE_REREQUESTS})"
            )
            try:
                self.request(target, self._clock() + MODE_CONFIRM_S, status)
            except CommandRefused as exc:
                status(f"{target} refused again: {exc}")
        mode = watch.mode
        try:
            self.disarm(2.0)
            after = "disarmed"
        except VehicleLinkError as exc:
            after = f"DISARM FAILED ({exc}): the vehicle may still be armed"
        switch = "COM_RC_IN_MODE" if self._px4() else "MODE_CH"
        raise ModeLost(
            f"vehicle armed in {mode}, not {target}: set by {who}; {target} requested "
            f"{MODE_REREQUESTS} more times and not kept; {after}. Check the RC mode switch "
            f"({switch}) and INITIAL_MODE"
        )

    def _can_send(self) -> bool:
        return self._link.conn is not None and self._watch.target is not None

    def hold(self, timeout_s: float = 2.0) -> None:
        """Switch to HOLD (ArduPilot) or AUTO.LOITER (PX4). A requested hold is not a
        takeover. ``timeout_s`` > 0 waits for the heartbeat to confirm (raising
        ``CommandRefused``); 0 sends and returns (a refusal lands in the link's
        ``inbox.last_refusal``). Stop first: PX4's Hold loops back to where it engaged
        (recorded: 150 °/s turns from 2 m/s), ArduPilot's coasts without braking."""
        mode = self.hold_mode()
        self.engaged_mode = None
        self.requested_mode = mode
        if timeout_s <= 0:
            if self._can_send():
                self._cmd.send(mp.CMD_DO_SET_MODE, self.mode_params(mode))
            return
        self.request(mode, self._clock() + timeout_s, self._status)

    def set_mode(self, mode: str, timeout_s: float = 3.0) -> None:
        """Request a mode by name (``"GUIDED"``, ``"HOLD"``, ``"MANUAL"``; PX4 ``"OFFBOARD"``,
        ``"LOITER"``, ...) until the heartbeat confirms it; refusals are retried until
        ``timeout_s`` s, then ``CommandRefused``. Entering the guided mode this way does not
        arm, and does not clear ``pilot_took_over``."""
        autopilot = self._watch.autopilot()
        known = mp.PX4_MODE_NUMBERS if autopilot == "px4" else mp.ROVER_MODE_NUMBERS
        if mode not in known:
            raise ValueError(f"unknown {autopilot} mode {mode!r}; one of {', '.join(known)}")
        self.engaged_mode = None
        self.request(mode, self._clock() + timeout_s, self._status)

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Disarm (standing still); raises ``CommandRefused`` if refused. ``timeout_s`` 0
        sends and returns."""
        if timeout_s <= 0:
            if self._can_send():
                self._cmd.send(mp.CMD_COMPONENT_ARM_DISARM, (0.0,))
            return
        result, reason = self._cmd.command(mp.CMD_COMPONENT_ARM_DISARM, (0.0,), timeout_s)
        if result != mp.RESULT_ACCEPTED:
            raise CommandRefused(
                "MAV_CMD_COMPONENT_ARM_DISARM(disarm)", mp.result_name(result), reason
            )
