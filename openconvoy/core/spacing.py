"""Spacing policies σ: the desired following distance, measured along the path.

Every policy gives the desired *centre-to-centre* gap (the log's ``desired_gap_m``) to the
immediate predecessor at the ego's speed; to a vehicle ``m`` places ahead the desired
arc-length gap is the sum over the ``m`` pairs between. ``constant-distance`` is the
paper's (15 m centre to centre); ``constant-time-headway`` (CACC) and ``quadratic``
(M-CACC) add a bumper-to-bumper standstill distance plus a speed term to the two half
lengths, so a standstill of 2 m means 2 m between bumpers.

``kind`` may also name a plug-in (``mylab.spacing:Quadratic``, ``file.py:Name`` or an
``openconvoy.spacing`` entry point; ``core.plugins``) built with ``params``: any object
with ``pair_gap(speed_mps, ego_length_m, pred_length_m) -> float``, the desired
centre-to-centre gap (m) to the immediate predecessor (docs/your-controller.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

from openconvoy.core import plugins
from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError

SPACING_KINDS = ("constant-distance", "constant-time-headway", "quadratic")
CONSTANT_DISTANCE, CONSTANT_TIME_HEADWAY, QUADRATIC = range(3)
"""The built-in kinds as codes (their index in ``SPACING_KINDS``): what the rule
functions below take, so the batched kernels can call them compiled."""
_CODES = {kind: code for code, kind in enumerate(SPACING_KINDS)}


def time_headway_gap_m(speed_mps: float, standstill_m: float, headway_s: float) -> float:
    """Constant-time-headway bumper gap (m): ``standstill_m`` plus ``headway_s`` (s) of
    the speed (m/s; reversing counts as 0)."""
    return standstill_m + headway_s * max(speed_mps, 0.0)


def speed_gap_m(
    kind: int, speed_mps: float, standstill_m: float, headway_s: float, quadratic_s2_per_m: float
) -> float:
    """Bumper gap (m) of a speed-dependent policy (``kind`` ``CONSTANT_TIME_HEADWAY`` or
    ``QUADRATIC``) at ``speed_mps``: the time-headway gap, plus ``quadratic_s2_per_m``
    (s²/m) times the speed squared for ``QUADRATIC``."""
    gap = time_headway_gap_m(speed_mps, standstill_m, headway_s)
    if kind == QUADRATIC:
        v = max(speed_mps, 0.0)
        gap = gap + quadratic_s2_per_m * v * v
    return gap


def pair_gap_m(
    kind: int,
    speed_mps: float,
    distance_m: float,
    standstill_m: float,
    headway_s: float,
    quadratic_s2_per_m: float,
    half_lengths_m: float,
) -> float:
    """Desired centre-to-centre gap (m) to the immediate predecessor: ``distance_m`` for
    ``CONSTANT_DISTANCE``, else ``speed_gap_m`` plus ``half_lengths_m`` (half the sum of
    the two vehicles' lengths, m)."""
    if kind == CONSTANT_DISTANCE:
        return distance_m
    return (
        speed_gap_m(kind, speed_mps, standstill_m, headway_s, quadratic_s2_per_m) + half_lengths_m
    )


@dataclass(frozen=True)
class SpacingConfig:
    """σ's parameters (SI): ``distance_m`` for constant-distance; ``standstill_m``,
    ``headway_s`` (and ``quadratic_s2_per_m`` for quadratic) for the others."""

    kind: str = "constant-distance"
    distance_m: Annotated[float, Range(0.0, 1000.0, lo_open=True)] = 15.0
    standstill_m: Annotated[float, Range(0.0, 1000.0)] = 2.0
    headway_s: Annotated[float, Range(0.0, 60.0)] = 0.6
    quadratic_s2_per_m: Annotated[float, Range(0.0, 10.0)] = 0.01
    params: dict[str, Any] = field(default_factory=dict, hash=False)
    """A plug-in's keyword arguments (its ``kind`` a plug-in reference)."""

    def __post_init__(self) -> None:
        if self.kind not in SPACING_KINDS:
            self.plugin()  # a plug-in that loads, takes ``params`` and has pair_gap

    @property
    def is_plugin(self) -> bool:
        return self.kind not in SPACING_KINDS

    @property
    def code(self) -> int:
        """The built-in kind's code (``CONSTANT_DISTANCE`` ...; -1 for a plug-in)."""
        return _CODES.get(self.kind, -1)

    def plugin(self) -> Any:
        """A new instance of the plug-in ``kind`` names (``core.plugins.component``)."""
        where = f"spacing {self.kind!r} (built-in: {', '.join(SPACING_KINDS)})"
        plugin = plugins.component("spacing", self.kind, self.params, where)
        try:  # a gap at rest between two 4 m cars: a number >= 0, or one line now
            gap = float(plugin.pair_gap(0.0, 4.0, 4.0))
        except Exception as exc:  # noqa: BLE001 - the plug-in's code
            raise ConfigError(
                f"{where}: pair_gap(0, 4, 4) raised {type(exc).__name__}: {exc}"
            ) from None
        if not math.isfinite(gap) or gap < 0.0:
            raise ConfigError(f"{where}: pair_gap(0, 4, 4) = {gap}; expected a finite gap >= 0 m")
        return plugin


HIGHWAY_SPACING = SpacingConfig("constant-time-headway", standstill_m=2.0, headway_s=1.5)
"""Spacing for full-size cars at highway speed (the leaderboard's ``emergency-braking``
and ``highway-cut-in``): 2 m between bumpers at rest (the CACC standstill distance of
``emergency-braking``'s placement) plus 1.5 s of the ego's speed, 39.5 m between bumpers
at 25 m/s. 1.5 s is the low end of the time-gap range 1.5-2.2 s of which ISO 15622
(adaptive cruise control, "following capability") requires an ACC to offer one setting,
its shortest allowed setting being 0.8 s (the range as the standard is commonly quoted;
its text was not readable here). The presets' 15 m constant distance, the paper's
small-car spacing, leaves 10.2 m between bumpers at 25 m/s: with any loss the braking
rule (``core.safety``: the car ahead taken as braking at 8 m/s² since its newest
message) finds that unsafe within the first second and stops the follower for the
episode, and a cut-in leaves a gap nobody can stop in (docs/leaderboard.md)."""


class SpacingPolicy:
    """Desired gaps from a SpacingConfig."""

    def __init__(self, config: SpacingConfig) -> None:
        self.config = config
        self._plugin = config.plugin() if config.is_plugin else None
        self._code = config.code

    def pair_gap(self, speed: float, ego_length: float, pred_length: float) -> float:
        """Desired centre-to-centre gap (m) to the immediate predecessor at ``speed`` (m/s)."""
        if self._plugin is not None:
            return float(self._plugin.pair_gap(speed, ego_length, pred_length))
        c = self.config
        return pair_gap_m(
            self._code,
            speed,
            c.distance_m,
            c.standstill_m,
            c.headway_s,
            c.quadratic_s2_per_m,
            0.5 * (ego_length + pred_length),
        )

    def gap_to(self, ego: int, target: int, speed: float, lengths: Sequence[float]) -> float:
        """Desired arc-length gap (m) from vehicle ``ego`` to vehicle ``target`` ahead of it
        (``target`` < ``ego``): the sum of the pair gaps between them at ``speed``."""
        return sum(self.pair_gap(speed, lengths[j + 1], lengths[j]) for j in range(target, ego))


class GapChain:
    """``SpacingPolicy.gap_to`` for one convoy's fixed ``lengths``: the same sums, with the
    speed-free parts (half lengths; whole sums for ``constant-distance``) computed once,
    because a member asks for them every tick for every target."""

    def __init__(self, policy: SpacingPolicy, lengths: Sequence[float]) -> None:
        self.policy = policy
        self.lengths = list(lengths)
        self._halves = [
            0.5 * (self.lengths[j + 1] + self.lengths[j]) for j in range(len(lengths) - 1)
        ]
        self._constant: dict[tuple[int, int], float] = {}
        self._code = policy.config.code

    def gap_to(self, ego: int, target: int, speed: float) -> float:
        """Desired arc-length gap (m) from ``ego`` to ``target`` ahead of it at ``speed`` (m/s)."""
        c = self.policy.config
        if c.is_plugin or not 0 <= target <= ego <= len(self._halves):
            return self.policy.gap_to(ego, target, speed, self.lengths)
        if c.kind == "constant-distance":
            gap = self._constant.get((ego, target))
            if gap is None:
                d = c.distance_m
                gap = self._constant[(ego, target)] = sum(d for _ in range(target, ego))
            return gap
        base = speed_gap_m(self._code, speed, c.standstill_m, c.headway_s, c.quadratic_s2_per_m)
        return sum(base + h for h in self._halves[target:ego])
