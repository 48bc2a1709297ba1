"""The deploy runner's vehicle handling: connect, arm, setpoints and HOLD, and the safe finish.

Everything here talks to the autopilot through a ``VehicleLink``; the decisions (what to
command, when a failsafe holds) are the runner's and ``bridge.failsafes``'. Times are the
runner's injected monotonic clock (s).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from openconvoy.bridge.failsafes import DRIVE, STOP, LinkWatchdog, Verdict
from openconvoy.bridge.link import LinkTimeout, Telemetry, VehicleLink
from openconvoy.core.state import VehicleState

log = logging.getLogger(__name__)

HOLD_MODES = ("HOLD", "LOITER")
HOLD_BELOW_MPS = 0.1
"""HOLD is requested once the vehicle is this slow (m/s) under stop setpoints, or after
``brake_time_s``: PX4's Hold loops back to where it engaged (150 °/s turns from 2 m/s,
shared/sitl-px4 row 23) and ArduPilot's coasts without braking (4.4 s from 2 m/s against
1.9 s for a stop setpoint, shared/sitl rows 20, 23)."""
RECONNECT_PERIOD_S = 2.0
"""A lost connection is reopened at most this often (s)."""


class StopRequested(Exception):
    """A signal asked to stop before the loop was running (while connecting or arming)."""


def brake_time_s(v0: float) -> float:
    """How long stop setpoints are streamed before HOLD at most (s): braking from ``v0``
    m/s at 1 m/s² (ArduPilot's ATC_ACCEL_MAX) plus a second, 1-6 s."""
    return min(6.0, 1.0 + abs(v0))


class VehicleHandler:
    """One vehicle's autopilot side of a run.

    Args:
        link: the vehicle.
        watchdog: the failsafes' link watchdog (is the telemetry fresh?).
        vehicle_id: convoy index, for status lines.
        rate_hz: control rate, Hz (the braking stream's period at the finish).
        commanding: whether setpoints are sent at all (not dry-run, not passive).
        clock: monotonic clock (s); sleep: sleeps that many seconds.
        on_status: receives status lines.
        check_stop: raises ``StopRequested`` when a stop was asked for.
    """

    def __init__(
        self,
        link: VehicleLink,
        watchdog: LinkWatchdog,
        *,
        vehicle_id: int,
        rate_hz: float,
        commanding: bool,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        on_status: Callable[[str], None],
        check_stop: Callable[[], None],
    ) -> None:
        self.link = link
        self.watchdog = watchdog
        self.vehicle_id = vehicle_id
        self.rate_hz = rate_hz
        self.commanding = commanding
        self.clock = clock
        self.sleep = sleep
        self.on_status = on_status
        self.check_stop = check_stop
        self.tel: Telemetry | None = None
        """The newest telemetry (None before the first)."""
        self.armed_by_us = False
        self.arming = False  # prepare_and_arm was entered and did not return
        self._t_reconnect = -math.inf
        self._t_hold_sent = -math.inf
        self._t_stop = math.nan  # when the current stop-and-hold began (monotonic s)
        self._v_stop = 0.0  # speed then (m/s)

    # ------------------------------------------------------------------ start

    def connect(self, timeout_s: float) -> None:
        """Connect and wait for the first telemetry, within ``timeout_s`` (--connect-timeout)."""
        deadline = self.clock() + timeout_s
        while True:  # short attempts, so that a signal is obeyed while waiting
            self.check_stop()
            try:
                self.link.connect(min(1.0, max(0.05, deadline - self.clock())))
                break
            except LinkTimeout as exc:
                if self.clock() >= deadline:  # the attempt's own timeout is not the user's
                    why = str(exc).split(" within ")[0]
                    raise LinkTimeout(f"{why} within --connect-timeout {timeout_s:g} s") from None
        while self.tel is None:
            self.check_stop()
            self.tel = self.link.poll()
            if self.tel is None:
                if self.clock() > deadline:
                    raise TimeoutError(
                        f"no position telemetry from the vehicle within {timeout_s:g} s"
                    )
                self.sleep(0.01)

    def arm(self, timeout_s: float) -> None:
        """Arm, then stand still with the yaw at the current heading from the first moment."""
        self.on_status(f"vehicle {self.vehicle_id}: arming ({self.link.autopilot})")
        # Arming may wait ~40 s for the estimator: status lines come every retry, and a
        # signal meanwhile ends the run through ``check_stop``.
        self.arming = True
        self.link.prepare_and_arm(timeout_s, self._status_or_stop)
        self.armed_by_us, self.arming = True, False
        self.link.stop_motion()

    def _status_or_stop(self, line: str) -> None:
        self.on_status(line)
        self.check_stop()

    # ------------------------------------------------------------------ each tick

    def read(self, now: float) -> tuple[Telemetry, float]:
        """The newest telemetry (the last one when none arrived) and when it was read;
        reopens a lost link now and then."""
        tel = self.link.poll()
        if tel is not None:
            self.tel = tel
        assert self.tel is not None
        t_polled = self.clock()
        self._maybe_reconnect(now)
        return self.tel, t_polled

    def _maybe_reconnect(self, now: float) -> None:
        """A lost connection (TCP EOF, serial error) is reopened every 2 s, without
        blocking the tick (``reconnect(0)``: the link opens it in the background)."""
        if not self.link.lost or now - self._t_reconnect < RECONNECT_PERIOD_S:
            return
        self._t_reconnect = now
        try:
            self.link.reconnect(0.0)
        except Exception as exc:  # noqa: BLE001 - keep trying
            log.info("reconnect failed: %s", exc)

    def actuate(
        self,
        now: float,
        tel: Telemetry,
        own: VehicleState,
        verdict: Verdict,
        speed: float,
        heading_cmd: float,
    ) -> float:
        """Send the setpoint (and HOLD once braked, or after the braking time); the link
        clock time it went out, NaN if none did."""
        t_sent = math.nan
        if not self.commanding:
            return t_sent
        if verdict.command in (DRIVE, STOP) and self.link.send_setpoint(speed, heading_cmd):
            t_sent = self.clock()
        if not verdict.hold:
            self._t_stop = math.nan
        elif math.isnan(self._t_stop):
            self._t_stop, self._v_stop = now, abs(own.speed)
        if (
            verdict.hold
            and now - self._t_hold_sent >= 1.0
            and tel.mode not in HOLD_MODES
            and (
                abs(own.speed) < HOLD_BELOW_MPS or now - self._t_stop >= brake_time_s(self._v_stop)
            )
        ):
            self._t_hold_sent = now
            try:
                self.link.hold(0.0)
            except Exception as exc:  # noqa: BLE001 - a hold that cannot be sent is retried
                log.warning("HOLD not sent: %s", exc)
        return t_sent

    # ------------------------------------------------------------------ finish

    def secure(self, took_over: bool, drove: bool) -> None:
        """Leave the vehicle safe at the end of a run: braked and in HOLD when we armed it,
        HOLD and disarmed when interrupted while arming, disarmed (or loudly left armed) when
        taken over before the convoy ``drove``. Never raises."""
        vid = self.vehicle_id
        if self.commanding and self.armed_by_us and not took_over:
            try:
                self._brake_to_rest()
                self.link.hold(2.0)
            except Exception as exc:  # noqa: BLE001 - the log must still be saved
                log.warning("vehicle %d: HOLD at exit failed: %s", vid, exc)
        elif self.commanding and self.arming:
            # Interrupted while arming (a signal, a refusal, a lost mode): it may have armed
            # meanwhile. Standing still, so HOLD and disarm; never armed without HOLD.
            for step in (self.link.hold, self.link.disarm):
                try:
                    step(0.0)
                except Exception as exc:  # noqa: BLE001
                    log.warning("vehicle %d: HOLD/disarm after arming failed: %s", vid, exc)
        elif self.commanding and took_over and not drove and self.armed_by_us:
            self._disarm_if_at_rest()

    def _brake_to_rest(self) -> None:
        """Stream stop setpoints until the vehicle is slower than ``HOLD_BELOW_MPS`` (at
        most ``brake_time_s``), while the autopilot link is fresh."""
        tel = self.tel
        v0 = abs(tel.state.speed) if tel is not None else 0.0
        end = self.clock() + brake_time_s(v0)
        period = 1.0 / self.rate_hz
        while True:
            if not self.link.stop_motion():
                return  # taken over, or a PX4 stream that must not resume
            got = self.link.poll()
            tel = got or tel
            now = self.clock()
            if tel is None or abs(tel.state.speed) < HOLD_BELOW_MPS or now >= end:
                return
            if not self.watchdog.fresh(now, tel.t_telemetry, tel.t_heartbeat, not self.link.lost):
                return
            self.sleep(period)

    def _disarm_if_at_rest(self) -> None:
        """A takeover before the convoy drove (ArduPilot's RC mode switch setting MANUAL
        after GUIDED, say) must not leave the vehicle armed and forgotten: disarm it if it
        stands still, else say loudly that it is armed in someone else's hands."""
        vid = self.vehicle_id
        tel = self.link.poll() or self.tel
        mode = tel.mode if tel is not None else "?"
        if tel is not None and abs(tel.state.speed) < HOLD_BELOW_MPS:
            try:
                self.link.disarm(2.0)
                self.on_status(
                    f"vehicle {vid}: disarmed (taken over in {mode} before the convoy drove)"
                )
                return
            except Exception as exc:  # noqa: BLE001
                log.warning("vehicle %d: disarm failed: %s", vid, exc)
        self.on_status(
            f"vehicle {vid}: WARNING: left ARMED in {mode} (taken over before the convoy drove)"
        )
