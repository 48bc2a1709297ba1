"""``openconvoy.testing.waiting``: ports and waits."""

from __future__ import annotations

import socket
import time

import pytest

from openconvoy.testing import free_port, run_for, wait_for, wait_until


def test_a_free_port_can_be_bound() -> None:
    for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
        port = free_port(kind)
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", port))
            assert 1024 <= port <= 65535


class Counting:
    def __init__(self) -> None:
        self.polls = 0
        self.sent: list[tuple[float, float]] = []
        self.setpoints = self

    def poll(self) -> None:
        self.polls += 1

    def send(self, speed: float, heading: float) -> None:
        self.sent.append((speed, heading))


def test_waits_say_when_and_whether() -> None:
    link = Counting()
    assert wait_for(lambda: link.polls >= 3, 5.0, link) and link.polls == 3
    assert not wait_for(lambda: False, 0.05)
    t0 = time.monotonic()
    assert t0 <= wait_until(lambda: time.monotonic() > t0 + 0.03, 5.0) <= time.monotonic()
    with pytest.raises(AssertionError, match="timed out after 0.05 s waiting for the moon"):
        wait_until(lambda: False, 0.05, "the moon")
    run_for(link, 0.12, speed=1.0, heading=0.5, period=0.05)
    assert 2 <= len(link.sent) <= 3 and link.sent[0] == (1.0, 0.5)
