"""COMMAND_LONG to the autopilot, checked by its COMMAND_ACK; telemetry intervals.

Every command's answer is awaited (retrying without one) while the link keeps being
serviced, so heartbeats, telemetry and the PX4 keep-alive stream go on during the wait.
Telemetry is requested per message with ``MAV_CMD_SET_MESSAGE_INTERVAL``; a refused rate
is reported and retried lower down a ladder.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from openconvoy.bridge.link import CommandRefused, LinkTimeout, StatusCallback
from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.connection import MavConnection
from openconvoy.bridge.mavlink.watch import VehicleWatch

_REASON_BURST_S = 0.03  # after a refusal's first text, how long its other texts may take
_RATE_LADDER_HZ = (50.0, 40.0, 25.0, 20.0, 15.0, 10.0, 5.0, 4.0, 2.0, 1.0)
TELEMETRY_MESSAGES = (mp.MSG_GLOBAL_POSITION_INT, mp.MSG_ATTITUDE)
"""The messages whose intervals are requested (position and attitude)."""


class Commander:
    """Sends commands to the watched vehicle and waits for their answers.

    Args:
        clock: monotonic clock (s).
        link: the connection.
        watch: the vehicle's heartbeats, ACKs and texts.
        service: handles the link once (periodic sends, draining); called while waiting.
    """

    def __init__(
        self,
        clock: Callable[[], float],
        link: MavConnection,
        watch: VehicleWatch,
        service: Callable[[], None],
    ) -> None:
        self._clock = clock
        self._link = link
        self._watch = watch
        self._service = service

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Service the link until ``predicate()`` holds (True) or ``timeout_s`` s pass or
        the connection closes (False)."""
        deadline = self._clock() + timeout_s
        while True:
            self._service()
            if predicate():
                return True
            if self._clock() >= deadline or self._link.conn is None:
                return False
            time.sleep(0.005)

    def send(self, command: int, params: tuple[float, ...], confirmation: int = 0) -> None:
        """One COMMAND_LONG to the vehicle (parameters padded to seven), no waiting."""
        target = self._watch.target
        assert target is not None
        p = tuple(params) + (0.0,) * (7 - len(params))
        self._link.conn.mav.command_long_send(target[0], target[1], command, confirmation, *p)

    def command(
        self, command: int, params: tuple[float, ...], timeout_s: float = 1.5, tries: int = 3
    ) -> tuple[int, str]:
        """Send a COMMAND_LONG, retrying without an answer; (result, reason). Raises
        ``LinkTimeout`` without any COMMAND_ACK."""
        watch = self._watch
        if watch.target is None:
            raise LinkTimeout("vehicle not identified yet: call connect() first")
        t_sent = self._clock()
        for attempt in range(tries):
            watch.acks.pop(command, None)
            self.send(command, params, confirmation=attempt)
            if self.wait_until(lambda: command in watch.acks, timeout_s / tries):
                result = watch.acks[command][0]
                reason = ""
                if result != mp.RESULT_ACCEPTED:
                    # ArduPilot sends its reasons just after the ACK, one text per failed
                    # check within a millisecond (shared/sitl): wait for the first, then
                    # a moment for the rest of the burst.
                    if self.wait_until(lambda: bool(watch.reason(t_sent)), 0.1):
                        self.wait_until(lambda: False, _REASON_BURST_S)
                    reason = watch.refusal(t_sent - 0.5)
                return result, reason
        link = self._link
        raise LinkTimeout(
            f"no COMMAND_ACK for {mp.command_name(command)} within {timeout_s:g} s"
            + (f" ({link.lost_reason})" if link.eof else "")
        )

    def request_intervals(self, hz_wanted: float, status: StatusCallback) -> dict[str, float]:
        """SET_MESSAGE_INTERVAL per telemetry message, lowering refused rates; the
        accepted rate per message name (Hz). Raises ``CommandRefused`` when not even
        1 Hz is accepted."""
        rates: dict[str, float] = {}
        for msg_id in TELEMETRY_MESSAGES:
            name = mp.message_name(msg_id)
            hz = hz_wanted
            while True:
                result, reason = self.command(mp.CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz))
                if result == mp.RESULT_ACCEPTED:
                    rates[name] = hz
                    break
                lower = next((r for r in _RATE_LADDER_HZ if r < hz), None)
                why = f": {reason}" if reason else ""
                if lower is None:
                    raise CommandRefused(
                        f"MAV_CMD_SET_MESSAGE_INTERVAL({name} at {hz:g} Hz)",
                        mp.result_name(result),
                        reason,
                    )
                status(
                    f"{name} at {hz:g} Hz refused ({mp.result_name(result)}{why}); "
                    f"requesting {lower:g} Hz"
                )
                hz = lower
        return rates

    def resend_intervals(self, rates: dict[str, float], status: StatusCallback) -> None:
        """Send the accepted intervals again without waiting (a vehicle back after silence
        or a reboot forgets them); the answers are checked as they arrive."""
        if self._watch.target is None:
            return
        status("vehicle back after silence or a reboot: requesting telemetry again")
        for msg_id in TELEMETRY_MESSAGES:
            hz = rates.get(mp.message_name(msg_id))
            if hz:
                self.send(mp.CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / hz))
