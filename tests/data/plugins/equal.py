"""The paper's components as plug-ins: each computes what the built-in one computes, in
the same floating-point order, so a policy made of them reproduces ``paper`` to the byte."""

import math


class AllPredecessors:
    """ρ: keep every predecessor's messages."""

    def keeps(self, ego: int, sender: int, n_vehicles: int) -> bool:
        return sender < ego


class Always:
    """τ: broadcast at every check (the trigger's period_s grid), as ``periodic``."""

    def should_send(self, own, last_sent, now: float) -> bool:
        return True


class ConstantDistance:
    """σ: a fixed centre-to-centre gap (m)."""

    tunable = {"distance_m": (5.0, 30.0)}

    def __init__(self, distance_m: float = 15.0) -> None:
        self.distance_m = distance_m

    def pair_gap(self, speed_mps: float, ego_length_m: float, pred_length_m: float) -> float:
        return self.distance_m


class PD:
    """χ_v: v_ref + kp·e + kd·ė (m/s)."""

    tunable = {"kp": (0.05, 5.0), "kd": (0.1, 5.0)}

    def __init__(self, kp: float = 0.3, kd: float = 1.1, dt_s: float = 0.05) -> None:
        self.kp, self.kd, self.dt_s = kp, kd, dt_s

    def __call__(self, error_m: float, v_ref_mps: float, error_rate_mps: float) -> float:
        return v_ref_mps + self.kp * error_m + self.kd * error_rate_mps

    def reset(self) -> None:
        pass


class Stanley:
    """χ_θ: heading error + atan2(gain · cross-track, softening + |v|) (rad)."""

    def __init__(self, gain: float = 0.2, softening_mps: float = 0.5) -> None:
        self.gain, self.softening_mps = gain, softening_mps

    def __call__(self, cross_track_m, heading_error_rad, speed_mps, lookahead) -> float:
        return heading_error_rad + math.atan2(
            self.gain * cross_track_m, self.softening_mps + abs(speed_mps)
        )
