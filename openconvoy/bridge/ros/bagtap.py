"""``BagTap``: a V2V socket that also records every datagram in a run's ROS 2 bag
(``deploy --bag``): what went on the air (``tx``) and everything that came off it
(``rx``, before decoding, authentication and the emulated loss), bytes unchanged."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from openconvoy.comms.multicast import MAX_BATCH, Datagram, Transport


class BagTap:
    """Wraps ``transport`` (a ``comms.multicast.Transport``); ``bag`` is an
    ``openconvoy.bag.BagWriter``; ``wall`` the shared clock (s) that stamps each datagram."""

    def __init__(
        self, transport: Transport, bag: Any, vehicle_id: int, wall: Callable[[], float]
    ) -> None:
        self.transport, self.bag, self.vehicle_id, self.wall = transport, bag, vehicle_id, wall

    def send(self, data: bytes) -> None:
        self.transport.send(data)  # an OSError propagates: nothing went out, nothing recorded
        self.bag.v2v(self.wall(), self.vehicle_id, "tx", data)

    def recv_all(self, max_batch: int = MAX_BATCH) -> list[Datagram]:
        got = self.transport.recv_all(max_batch)
        if got:
            t = self.wall()
            for d in got:
                self.bag.v2v(t, self.vehicle_id, "rx", d.data)
        return got

    def close(self) -> None:
        self.transport.close()
