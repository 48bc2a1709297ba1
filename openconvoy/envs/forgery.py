"""A forger on the simulated channel, and the members' message authentication.

The fault ``forge:ID@T`` (``core.faults``) puts a station without the convoy's keys on the
link from ``T`` seconds on: every control tick it broadcasts a state claiming to be
vehicle ``ID``, ``FORGED_AHEAD_M`` ahead of where that vehicle really is, along its
heading, at its speed (what a forged "leader 1 km ahead" looks like).

Authentication is modelled, not computed: on vehicles each message is an ECDSA-signed
IEEE 1609.2 SPDU that a forger cannot produce (``comms.security.auth``); here each received message
is verified by ``Authentication.verify``, which a forged message fails and a member's
passes, and the failures are counted per receiver, as ``comms.security.auth`` counts them. With
authentication off (``[v2v] auth = "off"``, ``sim --auth off``) forged messages are
delivered, so an experiment can show what the attack does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from openconvoy.core.state import VehicleState

#: How far ahead of the claimed vehicle the forged state puts it, metres.
FORGED_AHEAD_M = 1000.0


class ForgedState(VehicleState):
    """A state a forger sent: the same fields, but it carries no valid signature."""

    __slots__ = ()


def forged_state(claimed: VehicleState) -> ForgedState:
    """The forger's message about ``claimed``: ``FORGED_AHEAD_M`` further along its heading."""
    c, s = math.cos(claimed.heading), math.sin(claimed.heading)
    return ForgedState(
        claimed.vehicle_id,
        claimed.t,
        claimed.x + FORGED_AHEAD_M * c,
        claimed.y + FORGED_AHEAD_M * s,
        claimed.speed,
        claimed.heading,
        claimed.accel,
        claimed.yaw_rate,
        claimed.length,
        claimed.width,
    )


class Authentication:
    """Per-receiver verification of received messages (on or off), with counters.

    ``rejected[r]``: messages receiver ``r`` dropped because they failed verification.
    """

    def __init__(self, n_vehicles: int, required: bool = True) -> None:
        self.required = required
        self.rejected = [0] * n_vehicles

    def reset(self) -> None:
        self.rejected = [0] * len(self.rejected)

    def verify(self, receiver: int, msg: VehicleState) -> bool:
        """Whether ``receiver`` accepts ``msg`` (counted when not)."""
        if self.required and isinstance(msg, ForgedState):
            self.rejected[receiver] += 1
            return False
        return True

    def deliver_forgeries(
        self, claimed: Sequence[VehicleState], inboxes: Sequence[list[VehicleState]]
    ) -> None:
        """Offer a forged copy of each ``claimed`` state to every other member: appended to
        ``inboxes[r]`` (index = convoy position) when receiver ``r`` accepts it."""
        for st in claimed:
            msg = forged_state(st)
            for r, inbox in enumerate(inboxes):
                if r != st.vehicle_id and self.verify(r, msg):
                    inbox.append(msg)
