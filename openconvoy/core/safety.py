"""The braking-aware minimum gap: the emergency-stop rule, the same in sim and on vehicles.

A vehicle must stop when the gap to the vehicle ahead, between bumpers, less the most it
can shrink if the vehicle ahead brakes at its limit from now on while the ego reacts
(``reaction_s`` at its speed) and then brakes at its own limit, falls below a margin
(``gap_reduction_m``: about ``v_ego·t_r + v_ego²/(2·a_ego) − v_pred²/(2·a_pred)``). An
older rule took the closing speed only, as if the vehicle ahead kept its speed: it fired
too late when that vehicle braked (issue 22, D48). A fixed centre-to-centre
minimum (1 m once) leaves 0.13 m between the bumpers of the small cars and no room to
brake at all (issue 10). ``envs.convoy_env`` and ``bridge.failsafes.Envelope`` both use
``BrakingGap``; the numbers come from the vehicle preset (``for_vehicle``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from openconvoy.core.errors import ConfigError

DEFAULT_MARGIN_LENGTHS = 0.25
"""Default margin between bumpers, in own vehicle lengths: 0.19-0.24 m for the small cars,
1.2 m for a car (below the 2 m CACC standstill distance, so a convoy at rest is not an
emergency)."""


CONTROL_PERIOD_S = 0.05
"""The control period the rule allows for by default (s): 20 Hz, the simulator's and
``deploy``'s rate."""


def bumper_gap(centre_gap_m: float, ego_length_m: float, pred_length_m: float) -> float:
    """Gap between bumpers (m) from the centre-to-centre gap and the two lengths."""
    return centre_gap_m - 0.5 * (ego_length_m + pred_length_m)


def gap_reduction_m(
    ego_mps: float,
    pred_mps: float,
    reaction_s: float,
    lag_s: float,
    ego_decel: float,
    pred_decel: float,
    ego_accel: float = 0.0,
) -> float:
    """The most the gap (m) shrinks from now on when the vehicle ahead, at ``pred_mps``
    (m/s, along the line between the two), brakes at ``pred_decel`` (m/s²; inf: it
    stops at once, a wall) from now, and the ego, at ``ego_mps`` and speeding up at
    ``ego_accel`` (m/s²; slowing counts as 0), keeps accelerating for ``reaction_s`` (s:
    its actuation delay and a control period) and then brakes through its speed loop: a
    first-order lag of
    ``lag_s`` (s) clipped at ``ego_decel`` (m/s², the simulator's ``lag`` plant). 0 when
    the gap only grows.

    The ego's stopping distance is ``v·t_r + v²/(2a) + a·τ²/2`` while the lag saturates
    at the limit (``v > a·τ``), else ``v·t_r + v·τ``; the predecessor's ``v_p²/(2a_p)``.
    When the ego brakes harder the two speeds may meet while both still move: there the
    gap is smallest, taken with the lag as a further delay (conservative). The batched
    kernels call this very function, compiled (``envs.vector.jit.rules``).
    """
    v0 = ego_mps if ego_mps > 0.0 else 0.0
    vp = pred_mps if pred_mps > 0.0 else 0.0
    up = ego_accel if ego_accel > 0.0 else 0.0
    ve = v0 + up * reaction_s  # the speed it starts braking from
    pred_stop = 0.0 if math.isinf(pred_decel) else vp * vp / (2.0 * pred_decel)
    react = v0 * reaction_s + 0.5 * up * reaction_s * reaction_s
    knee = ego_decel * lag_s
    if ve > knee:
        ego_stop = react + ve * ve / (2.0 * ego_decel) + 0.5 * knee * lag_s
    else:
        ego_stop = react + ve * lag_s
    worst = ego_stop - pred_stop
    if ego_decel > pred_decel:
        # speeds meet at t*: ve - a_e (t* - t_r) = vp - a_p t*, with t_r = reaction + lag
        tr = reaction_s + lag_s
        ts = (ve + ego_decel * tr - vp) / (ego_decel - pred_decel)
        tb = ts - tr
        if tb > 0.0 and vp - pred_decel * ts > 0.0:
            ego_x = ve * ts - 0.5 * ego_decel * tb * tb  # (at ve from the start: more)
            pred_x = vp * ts - 0.5 * pred_decel * ts * ts
            worst = max(worst, ego_x - pred_x)
    return worst if worst > 0.0 else 0.0


def stopping_distance_m(
    closing_mps: float,
    ego_mps: float,
    pred_decel_mps2: float,
    ego_accel_mps2: float,
    rule: Sequence[float],
) -> float:
    """``BrakingGap.stopping_distance`` on floats: ``rule`` is the rule's numbers
    ``(decel_mps2, reaction_s, margin_m, lag_s)`` (``BrakingGap.numbers``); ``ego_mps``
    NaN when the ego's speed is unknown."""
    closing = closing_mps if math.isfinite(closing_mps) else 0.0
    if not math.isfinite(ego_mps):
        ego, pred = closing, 0.0
    else:
        ego, pred = ego_mps, ego_mps - closing
    return gap_reduction_m(ego, pred, rule[1], rule[3], rule[0], pred_decel_mps2, ego_accel_mps2)


def too_close(
    bumper_gap_m: float,
    closing_mps: float,
    ego_mps: float,
    pred_decel_mps2: float,
    ego_accel_mps2: float,
    rule: Sequence[float],
) -> bool:
    """``BrakingGap.too_close`` on floats (``stopping_distance_m``'s arguments): True when
    the gap is known and the clearance left after braking is below the margin. The
    batched kernels call this function compiled (``envs.vector.jit.rules``)."""
    if not math.isfinite(bumper_gap_m):
        return False
    left = bumper_gap_m - stopping_distance_m(
        closing_mps, ego_mps, pred_decel_mps2, ego_accel_mps2, rule
    )
    return left < rule[2]


CLEAR, BLIND, TOO_CLOSE = 0, 1, 2
"""``verdict``'s answers: drive on; brake to rest while the predecessor is unheard (not
latched); the emergency stop (latched by the world)."""


def verdict(
    known: bool,
    bumper_gap_m: float,
    closing_mps: float,
    ego_mps: float,
    pred_decel_mps2: float,
    ego_accel_mps2: float,
    rule: Sequence[float],
) -> int:
    """The braking rule's answer for a follower: ``TOO_CLOSE`` when ``too_close`` on the
    gap (m, between bumpers) read from the predecessor's messages or a ranging sensor;
    ``BLIND`` when there is no reading at all (``known`` False: the predecessor never
    heard, no ranging); else ``CLEAR``. The batched kernels call this function compiled
    (``envs.vector.jit.rules``).

    ``BLIND`` closes the hole of issue 22's leaderboard collisions: an unheard predecessor
    used to switch the rule off, so a follower that heard only the leader drove at or
    above cruise speed into a predecessor braking at its limit (its policy's stop for want
    of messages, or its own emergency stop), and found the gap, once its first message
    came 0.6-1.8 s later, 2.6-3.8 m short of what braking needs (``emergency-braking``,
    PER 0.8 and Gilbert-Elliott 0.6). Nothing bounds where an unheard vehicle is, so the
    follower brakes until it hears it, as its predecessor may have since the start.
    """
    if not known:
        return BLIND
    if too_close(bumper_gap_m, closing_mps, ego_mps, pred_decel_mps2, ego_accel_mps2, rule):
        return TOO_CLOSE
    return CLEAR


@dataclass(frozen=True)
class BrakingGap:
    """The rule's numbers, SI.

    Attributes:
        decel_mps2: the ego's braking limit (m/s², positive).
        reaction_s: time from deciding to brake to the first change of speed (the
            actuation delay, s).
        margin_m: the stop fires when the clearance left after braking is below this (m,
            between bumpers).
        lag_s: the speed loop's time constant (s): a first-order lag clipped at
            ``decel_mps2`` (``gap_reduction_m``).
    """

    decel_mps2: float
    reaction_s: float
    margin_m: float
    lag_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("decel_mps2", "reaction_s", "margin_m", "lag_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ConfigError(f"braking gap {name} must be a finite number, got {value!r}")
        if self.decel_mps2 <= 0 or self.reaction_s < 0 or self.margin_m < 0 or self.lag_s < 0:
            raise ConfigError(
                "braking gap needs decel_mps2 > 0, reaction_s >= 0, margin_m >= 0 and "
                f"lag_s >= 0, got {self.decel_mps2}, {self.reaction_s}, {self.margin_m}, "
                f"{self.lag_s}"
            )

    @property
    def numbers(self) -> tuple[float, float, float, float]:
        """``(decel_mps2, reaction_s, margin_m, lag_s)``: what the plain rule functions
        (``too_close``) take."""
        return (self.decel_mps2, self.reaction_s, self.margin_m, self.lag_s)

    def stopping_distance(
        self,
        closing_mps: float,
        ego_mps: float | None = None,
        pred_decel_mps2: float = math.inf,
        ego_accel_mps2: float = 0.0,
    ) -> float:
        """Distance (m) the gap may shrink before both vehicles are at rest if the one
        ahead brakes at ``pred_decel_mps2`` from now (``gap_reduction_m``). ``closing_mps``
        (m/s, positive = closing) gives the predecessor's speed as ``ego_mps − closing``.
        ``ego_mps`` None (the ego's speed unknown): the closing speed is taken as the
        ego's and the predecessor as at rest (``closing²/(2a) + reaction·closing``)."""
        ego = math.nan if ego_mps is None else ego_mps
        return stopping_distance_m(closing_mps, ego, pred_decel_mps2, ego_accel_mps2, self.numbers)

    def clearance(
        self,
        bumper_gap_m: float,
        closing_mps: float,
        ego_mps: float | None = None,
        pred_decel_mps2: float = math.inf,
        ego_accel_mps2: float = 0.0,
    ) -> float:
        """Bumper gap left (m) after both brake (``stopping_distance``)."""
        return bumper_gap_m - self.stopping_distance(
            closing_mps, ego_mps, pred_decel_mps2, ego_accel_mps2
        )

    def too_close(
        self,
        bumper_gap_m: float,
        closing_mps: float,
        ego_mps: float | None = None,
        pred_decel_mps2: float = math.inf,
        ego_accel_mps2: float = 0.0,
    ) -> bool:
        """True when the gap is known and the clearance left is below the margin."""
        ego = math.nan if ego_mps is None else ego_mps
        return too_close(
            bumper_gap_m, closing_mps, ego, pred_decel_mps2, ego_accel_mps2, self.numbers
        )

    def reason(
        self,
        bumper_gap_m: float,
        closing_mps: float,
        ego_mps: float | None = None,
        pred_decel_mps2: float = math.inf,
        ego_accel_mps2: float = 0.0,
    ) -> str:
        """The log line: gap, closing speed, own speed and what braking would leave."""
        own = "" if ego_mps is None else f" at {ego_mps:.2f} m/s"
        left = self.clearance(bumper_gap_m, closing_mps, ego_mps, pred_decel_mps2, ego_accel_mps2)
        return (
            f"gap {bumper_gap_m:.2f} m between bumpers closing at {closing_mps:.2f} m/s{own} "
            f"leaves {left:.2f} m after braking (margin {self.margin_m:.2f} m)"
        )


def for_vehicle(
    decel_max_mps2: float,
    actuation_delay_s: float,
    speed_lag_s: float,
    length_m: float,
    margin_m: float | None = None,
    period_s: float = CONTROL_PERIOD_S,
) -> BrakingGap:
    """The rule for a vehicle preset's numbers; ``margin_m`` None = the default
    (``DEFAULT_MARGIN_LENGTHS`` of the vehicle's length). The reaction is the actuation
    delay and one control period ``period_s`` (s: the stop goes out at the next tick)."""
    margin = DEFAULT_MARGIN_LENGTHS * length_m if margin_m is None else margin_m
    return BrakingGap(decel_max_mps2, actuation_delay_s + period_s, margin, speed_lag_s)
