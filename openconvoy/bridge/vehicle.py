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
REST_MPS = 0.3
"""Reported speeds below this (m/s) count as at rest for the end of a run and the watch
below: PX4's estimated speed (GLOBAL_POSITION_INT) stays at 0.19-0.22 m/s for a rover
standing still (shared/sitl-px4, speed steps "1 -> 0": true speed 0)."""
UNCOMMANDED_MPS = 0.5
"""A vehicle held at rest (HOLD/LOITER, armed) faster than this (m/s) moves uncommanded."""
UNCOMMANDED_M = 1.0
"""... or farther than this (m) from where it came to rest: PX4's Hold is not a parking
brake (shared/AUTOPILOTS.md: with its position estimate drifting ~0.5 m at rest, past the
acceptance radius, PX4 drove loops around its hold point at up to 2.2 m/s in 2 of 14 held
vehicles); GPS noise at rest stays well below a metre."""
REST_WAIT_S = 5.0
"""At the end, how long to wait for a vehicle to come to rest before disarming it (s)."""


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
        stay_armed: leave the vehicle armed in HOLD at the end (``--stay-armed``); by
            default a run ends with its vehicle at rest and disarmed.
        on_event: records a failsafe-like event (uncommanded motion) for the metadata.
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
        stay_armed: bool = False,
        on_event: Callable[[str], None] | None = None,
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
        self.stay_armed = stay_armed
        self.on_event = on_event or (lambda why: None)
        self.autopilot: str | None = None
        """The firmware the vehicle identified itself as at connect (kept after its loss)."""
        self.uncommanded = ""
        """The uncommanded motion seen while holding the vehicle ("" when none)."""
        self._rest: tuple[float, float] | None = None  # where it came to rest in HOLD (ENU m)
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
        self.autopilot = _identified(self.link)
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
        self.link.modes.prepare_and_arm(timeout_s, self._status_or_stop)
        self.armed_by_us, self.arming = True, False
        self.link.setpoints.stop()

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
        if verdict.command in (DRIVE, STOP) and self.link.setpoints.send(speed, heading_cmd):
            t_sent = self.clock()
        self._watch_rest(tel, own)
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
                self.link.modes.hold(0.0)
            except Exception as exc:  # noqa: BLE001 - a hold that cannot be sent is retried
                log.warning("HOLD not sent: %s", exc)
        return t_sent

    def _watch_rest(self, tel: Telemetry, own: VehicleState) -> None:
        """While the vehicle stands armed in its hold mode, report (once) any motion it makes
        on its own — faster than ``UNCOMMANDED_MPS`` or farther than ``UNCOMMANDED_M`` from
        where it came to rest — and disarm it unless ``stay_armed``."""
        if not (self.armed_by_us and tel.armed and tel.mode in HOLD_MODES):
            self._rest = None
            return
        if self._rest is None:
            if abs(own.speed) < REST_MPS:
                self._rest = (own.x, own.y)
            return
        moved = math.hypot(own.x - self._rest[0], own.y - self._rest[1])
        if self.uncommanded or (abs(own.speed) <= UNCOMMANDED_MPS and moved <= UNCOMMANDED_M):
            return
        self.uncommanded = (
            f"uncommanded motion in {tel.mode}: {abs(own.speed):.2f} m/s, "
            f"{moved:.1f} m from where it came to rest"
        )
        self.on_event(self.uncommanded)
        action = "left armed (--stay-armed)" if self.stay_armed else "disarming it"
        self.on_status(f"vehicle {self.vehicle_id}: WARNING: {self.uncommanded}; {action}")
        if not self.stay_armed:
            try:
                self.link.modes.disarm(0.0)
            except Exception as exc:  # noqa: BLE001 - retried at the finish
                log.warning("vehicle %d: disarm not sent: %s", self.vehicle_id, exc)

    # ------------------------------------------------------------------ finish

    def secure(self, took_over: bool, drove: bool, autopilot_failsafe: bool = False) -> None:
        """Leave the vehicle safe at the end of a run: braked, in HOLD and disarmed when we
        armed it (still armed in HOLD with ``stay_armed``); HOLD and disarmed when
        interrupted while arming; disarmed at rest after a takeover before the convoy
        ``drove``, or after the autopilot's own failsafe took it (nobody at the controls);
        left alone when a person took over while driving. Never raises."""
        vid = self.vehicle_id
        if not self.commanding:
            return
        if self.armed_by_us and not took_over:
            if not self._link_usable():
                self.on_status(
                    f"vehicle {vid}: HOLD and disarm at exit not sent: {self._why_unusable()}; "
                    "the autopilot's own failsafe has the vehicle"
                )
                return
            try:
                self._brake_to_rest()
                self.link.modes.hold(2.0)
            except Exception as exc:  # noqa: BLE001 - the log must still be saved
                log.warning("vehicle %d: HOLD at exit failed: %s", vid, exc)
            self._disarm_at_end("in HOLD")
        elif self.arming:
            # Interrupted while arming (a signal, a refusal, a lost mode): it may have armed
            # meanwhile. Standing still, so HOLD and disarm; never armed without HOLD.
            for step in (self.link.modes.hold, self.link.modes.disarm):
                try:
                    step(0.0)
                except Exception as exc:  # noqa: BLE001
                    log.warning("vehicle %d: HOLD/disarm after arming failed: %s", vid, exc)
        elif took_over and self.armed_by_us and (not drove or autopilot_failsafe):
            self._disarm_if_at_rest(drove)

    def _link_usable(self) -> bool:
        """Whether the autopilot can be told anything: connected, identified and heard from
        within the watchdog's timeouts."""
        tel = self.link.poll() or self.tel
        if tel is not None:
            self.tel = tel
        if self.link.lost or tel is None:
            return False
        return self.watchdog.fresh(self.clock(), tel.t_telemetry, tel.t_heartbeat, True)

    def _why_unusable(self) -> str:
        if self.link.lost:
            return "the autopilot link is lost (connection closed)"
        return "the autopilot link is lost (no telemetry or heartbeat)"

    def _wait_for_rest(self, timeout_s: float) -> Telemetry | None:
        """Poll until the vehicle is slower than ``REST_MPS`` (at most ``timeout_s`` s);
        the newest telemetry."""
        end = self.clock() + timeout_s
        tel = self.tel
        while True:
            tel = self.link.poll() or tel
            if tel is None or abs(tel.state.speed) < REST_MPS or self.clock() >= end:
                return tel
            self.sleep(1.0 / self.rate_hz)

    def _disarm_at_end(self, where: str) -> None:
        """Disarm at rest, or say that the vehicle stays armed and why. Both firmwares
        accept a disarm at rest in their hold mode (recorded: PX4 "Disarmed by external
        command" in Hold, shared/sitl-px4 boot_and_arm 6.38 s; ArduPilot Rover, shared/sitl
        boot_and_arm 26.97 s), and a disarmed rover cannot drive loops around a hold point
        (shared/AUTOPILOTS.md: "End at rest disarmed")."""
        vid = self.vehicle_id
        if self.stay_armed:
            self.on_status(
                f"vehicle {vid}: left ARMED {where} (--stay-armed); nobody watches it once "
                "this process ends (PX4's Hold can drive around its hold point)"
            )
            return
        tel = self._wait_for_rest(REST_WAIT_S)
        if tel is not None and abs(tel.state.speed) >= REST_MPS:
            self.on_status(
                f"vehicle {vid}: WARNING: still moving at {abs(tel.state.speed):.2f} m/s "
                f"{REST_WAIT_S:g} s after HOLD; disarming anyway"
            )
        try:
            self.link.modes.disarm(2.0)
            self.on_status(f"vehicle {vid}: at rest {where}, disarmed")
        except Exception as exc:  # noqa: BLE001
            self.on_status(f"vehicle {vid}: WARNING: disarm at exit failed ({exc}): left ARMED")

    def _brake_to_rest(self) -> None:
        """Stream stop setpoints until the vehicle is slower than ``HOLD_BELOW_MPS`` (at
        most ``brake_time_s``), while the autopilot link is fresh."""
        tel = self.tel
        v0 = abs(tel.state.speed) if tel is not None else 0.0
        end = self.clock() + brake_time_s(v0)
        period = 1.0 / self.rate_hz
        while True:
            if not self.link.setpoints.stop():
                return  # taken over, or a PX4 stream that must not resume
            got = self.link.poll()
            tel = got or tel
            now = self.clock()
            if tel is None or abs(tel.state.speed) < HOLD_BELOW_MPS or now >= end:
                return
            if not self.watchdog.fresh(now, tel.t_telemetry, tel.t_heartbeat, not self.link.lost):
                return
            self.sleep(period)

    def _disarm_if_at_rest(self, drove: bool = False) -> None:
        """A takeover before the convoy drove (ArduPilot's RC mode switch setting MANUAL
        after GUIDED, say), or the autopilot's own failsafe (PX4's offboard-loss POSCTL,
        which brakes straight), must not leave the vehicle armed and forgotten: disarm it
        once it stands still (``stay_armed``: leave it), else say loudly that it is armed
        in someone else's hands."""
        vid = self.vehicle_id
        tel = self._wait_for_rest(REST_WAIT_S if drove else 0.0) if not self.link.lost else None
        tel = tel or self.tel
        mode = tel.mode if tel is not None else "?"
        why = "its failsafe took it" if drove else "taken over before the convoy drove"
        if self.stay_armed:
            self.on_status(f"vehicle {vid}: left ARMED in {mode} (--stay-armed; {why})")
            return
        if tel is not None and abs(tel.state.speed) < REST_MPS and not self.link.lost:
            try:
                self.link.modes.disarm(2.0)
                self.on_status(f"vehicle {vid}: disarmed ({why}, in {mode})")
                return
            except Exception as exc:  # noqa: BLE001
                log.warning("vehicle %d: disarm failed: %s", vid, exc)
        self.on_status(f"vehicle {vid}: WARNING: left ARMED in {mode} ({why})")


def _identified(link: VehicleLink) -> str | None:
    """The autopilot a connected link identified (None when it cannot say)."""
    try:
        return str(link.autopilot)
    except Exception:  # noqa: BLE001
        return None
