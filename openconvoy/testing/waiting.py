"""Real-time helpers for tests on sockets and threads: free localhost ports, polling until
something holds, driving a link for a while."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable
from typing import Any

POLL_S = 0.01
"""How often (s) the waits check their condition."""


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A localhost port nobody uses right now (UDP by default; ``socket.SOCK_STREAM``: TCP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _poll_until(
    predicate: Callable[[], bool], timeout: float, each: Callable[[], Any] | None = None
) -> float | None:
    """The monotonic time ``predicate()`` first held (``each()`` called before every
    check), or None when ``timeout`` s passed first."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if each is not None:
            each()
        if predicate():
            return time.monotonic()
        time.sleep(POLL_S)
    return None


def wait_for(predicate: Callable[[], bool], timeout: float, link: Any = None) -> bool:
    """Poll ``link`` (when given) until ``predicate`` holds or ``timeout`` s pass: whether
    it held."""
    return _poll_until(predicate, timeout, None if link is None else link.poll) is not None


def wait_until(pred: Callable[[], bool], timeout: float, what: str = "") -> float:
    """Sleep-poll until ``pred()``; returns the monotonic time it became true, or raises
    AssertionError naming ``what`` after ``timeout`` s."""
    at = _poll_until(pred, timeout)
    if at is None:
        raise AssertionError(f"timed out after {timeout} s waiting for {what or pred}")
    return at


def run_for(
    link: Any,
    seconds: float,
    speed: float | None = None,
    heading: float | None = None,
    period: float = 0.05,
) -> None:
    """Poll the link (and send a setpoint when given) every ``period`` s for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        link.poll()
        if speed is not None and heading is not None:
            link.setpoints.send(speed, heading)
        time.sleep(period)


__all__ = ["POLL_S", "free_port", "run_for", "wait_for", "wait_until"]


def drive_on_heading(
    link: Any, heading_rad: float, speed_mps: float = 1.5, timeout_s: float = 25.0
) -> tuple[Callable[[], bool], list[float]]:
    """Drive ``link`` (a ``VehicleLink``, armed) at ``speed_mps`` on ``heading_rad`` until
    its telemetry shows it faster than 1 m/s within 0.1 rad of the heading (``AssertionError``
    after ``timeout_s``); returns the one-tick step (poll, send the setpoint, record the
    telemetry's x, m; True while on the heading) and the recorded x, for further checks."""
    xs: list[float] = []

    def step() -> bool:
        tel = link.poll()
        link.setpoints.send(speed_mps, heading_rad)
        if tel is None:
            return False
        xs.append(tel.state.x)
        return (
            tel.state.speed > 1.0
            and abs(math.remainder(tel.state.heading - heading_rad, 2 * math.pi)) < 0.1
        )

    assert wait_for(step, timeout_s), f"the vehicle did not settle on {heading_rad:.2f} rad"
    return step, xs
