"""A spacing policy σ: standstill + headway × v + q × v² between bumpers (M-CACC's shape).

With ``quadratic_s2_per_m = 0`` it is ``constant-time-headway`` to the bit. Use it from a
policy TOML (``examples/my_spacing.toml``)::

    [policy.member.spacing]
    kind = "examples/my_spacing.py:Quadratic"
    params = { standstill_m = 2.0, headway_s = 0.6, quadratic_s2_per_m = 0.01 }
"""


class Quadratic:
    """``pair_gap``: the desired centre-to-centre gap (m) to the immediate predecessor."""

    tunable = {"headway_s": (0.3, 2.0), "quadratic_s2_per_m": (0.0, 0.05)}

    def __init__(
        self, standstill_m: float = 2.0, headway_s: float = 0.6, quadratic_s2_per_m: float = 0.0
    ) -> None:
        self.standstill_m, self.headway_s, self.q = standstill_m, headway_s, quadratic_s2_per_m

    def pair_gap(self, speed_mps: float, ego_length_m: float, pred_length_m: float) -> float:
        v = max(speed_mps, 0.0)
        gap = self.standstill_m + self.headway_s * v + self.q * v * v  # bumper to bumper
        return gap + 0.5 * (ego_length_m + pred_length_m)  # centre to centre
