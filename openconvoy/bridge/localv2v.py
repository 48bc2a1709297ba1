"""An in-process V2V bus with the same face as ``comms.v2v.V2V``, for tests and benchmarks.

Several ``DeployRunner`` objects in one process (or one runner with injected messages)
exchange vehicle states through a ``LocalBus`` instead of multicast BSMs. The loss model
(``comms.loss``) is applied at the receiver or the sender, as ``deploy --per`` does.
Nothing here opens a socket.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.comms.v2v import Counters
from openconvoy.core.errors import ConfigError
from openconvoy.core.plans import Plan
from openconvoy.core.state import VehicleState


@dataclass(frozen=True)
class Received:
    """One message heard: the sender's state (``t`` = sender time), our receive time, and
    whether it is a convoy-wide abort. Same attributes as ``comms.v2v.Received``."""

    state: VehicleState | None
    t_rx: float
    abort: bool = False
    source: str = "local"
    plan: Plan | None = None


class LocalBus:
    """Shared by the ``LocalV2V`` endpoints of one process; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queues: list[deque[tuple[VehicleState | Plan | None, bool]]] = []

    def attach(self) -> deque[tuple[VehicleState | Plan | None, bool]]:
        q: deque[tuple[VehicleState | Plan | None, bool]] = deque(maxlen=10000)
        with self._lock:
            self._queues.append(q)
        return q

    def publish(
        self, sender: deque, state: VehicleState | Plan | None, abort: bool = False
    ) -> None:
        with self._lock:
            for q in self._queues:
                if q is not sender:
                    q.append((state, abort))

    def abort(self) -> None:
        """A convoy-wide stop, as ``openconvoy abort`` broadcasts."""
        self.publish(deque(), None, abort=True)


class LocalV2V:
    """One vehicle's endpoint on a ``LocalBus``.

    ``counters`` (``comms.v2v.Counters``) and ``metadata`` mean what they mean for
    ``comms.v2v.V2V``.
    """

    def __init__(
        self,
        bus: LocalBus,
        loss: LossConfig | None = None,
        drop_at: str = "receiver",
        seed: int = 0,
    ) -> None:
        if drop_at not in ("receiver", "sender"):
            raise ConfigError(f"drop_at must be 'receiver' or 'sender', got {drop_at!r}")
        self.bus = bus
        self.loss_config = loss or LossConfig()
        self.drop_at = drop_at
        self._loss = self.loss_config.make()
        self._loss.reset(np.random.default_rng(seed))
        self._q = bus.attach()
        self.counters = Counters()

    def send(self, state: VehicleState, now: float) -> bool:
        if self.drop_at == "sender" and self._loss.lost(now):
            self.counters.lost += 1
            return False
        self.counters.sent += 1
        self.bus.publish(self._q, state)
        return True

    def send_plan(self, plan: Plan, now: float) -> bool:
        """Publish own ``plan`` (``core.plans``) beside the state, as ``V2V.send_plan``."""
        if self.drop_at == "sender" and self._loss.lost(now):
            self.counters.lost += 1
            return False
        self.bus.publish(self._q, plan)
        return True

    def poll(self, now: float, budget_s: float | None = None) -> list[Received]:
        """Every message waiting (in-process: ``budget_s`` is not needed)."""
        out: list[Received] = []
        while self._q:
            state, abort = self._q.popleft()
            if abort:
                self.counters.received += 1
                self.counters.aborts += 1
                out.append(Received(None, now, abort=True))
                continue
            if self.drop_at == "receiver" and self._loss.lost(now):
                self.counters.lost += 1
                continue
            self.counters.received += 1
            if isinstance(state, Plan):
                self.counters.plans += 1
                out.append(Received(None, now, plan=state))
            else:
                out.append(Received(state, now))
        return out

    @property
    def metadata(self) -> dict[str, Any]:
        return {
            "transport": "local",
            "per": self.loss_config.per,
            "loss_model": self.loss_config.model,
            "drop_at": self.drop_at,
        }

    def close(self) -> None:
        pass
