"""A V2V endpoint for tests of the deploy runner: it delivers exactly what the test puts in."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from openconvoy.comms.v2v import Counters
from openconvoy.core.state import VehicleState


@dataclass
class Heard:
    """One delivered message, as the runner reads it: the sender's ``state`` (None: an
    abort without a position) and the convoy-wide ``abort`` flag."""

    state: VehicleState | None
    abort: bool = False


class ReplayV2V:
    """Delivers exactly the messages the test puts in ``inbox`` (each at the next poll);
    ``counters`` count what was sent and received, as ``comms.v2v.V2V``'s do."""

    def __init__(self) -> None:
        self.counters = Counters()
        self.inbox: list[VehicleState] = []
        self.metadata: dict[str, Any] = {}

    def send(self, state: VehicleState, now: float) -> bool:
        """Counted, sent nowhere."""
        self.counters.sent += 1
        return True

    def poll(self, now: float, budget_s: float | None = None) -> list[Heard]:
        """The inbox's messages, emptying it."""
        out, self.inbox = [Heard(s) for s in self.inbox], []
        self.counters.received += len(out)
        return out

    def close(self) -> None:
        """Nothing to release."""


__all__ = ["Heard", "ReplayV2V"]
