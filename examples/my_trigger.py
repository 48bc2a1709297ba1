"""A trigger τ: broadcast when the speed or the heading changed since the last message,
or after a maximum silence. Asked on the trigger's ``period_s`` grid."""

import math

from openconvoy.core.state import VehicleState


class SpeedOrTurn:
    """``should_send(own, last_sent, now)``: True to broadcast ``own`` now (``now`` in s)."""

    tunable = {"speed_threshold_mps": (0.05, 1.0)}

    def __init__(
        self,
        speed_threshold_mps: float = 0.2,
        heading_threshold_rad: float = 0.05,
        max_silence_s: float = 0.3,
    ) -> None:
        self.speed_threshold_mps = speed_threshold_mps
        self.heading_threshold_rad = heading_threshold_rad
        self.max_silence_s = max_silence_s

    def should_send(self, own: VehicleState, last_sent: VehicleState | None, now: float) -> bool:
        if last_sent is None or now - last_sent.t >= self.max_silence_s - 1e-9:
            return True
        turn = (own.heading - last_sent.heading + math.pi) % (2 * math.pi) - math.pi
        return (
            abs(own.speed - last_sent.speed) > self.speed_threshold_mps
            or abs(turn) > self.heading_threshold_rad
        )
