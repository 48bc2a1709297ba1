"""The classical policy: σ, χ_v and χ_θ composed, reading the observation's named view.

σ, read along the path: each kept predecessor ``j`` asks for the ego to sit at the point
on ``j``'s trail at the desired distance behind it; the sum of squared distances between
those points and the ego's position one step ahead is smallest at their mean, so the
target lies ``mean_j(spacing_error_j)`` metres ahead along the path (the paper's sum of
distances, with squares so the argmin is unique for two predecessors). χ_v turns that
error plus the nearest predecessor's speed into a speed setpoint; χ_θ steers onto the
nearest predecessor's trail.

Stale targets only slow (issue 10). The mean runs over the fresh targets (messages no
older than ``MemberConfig.fresh_age_s``, the ladder's ``degrade_after_s``); the nearest fresh predecessor caps the speed
at what it alone asks for, so a leader far ahead can no longer outweigh a stopped
predecessor; each stale target (which the member already dead-reckons as braking) caps it
at its own term of the mean — ``min(mean of the others, each one) <= mean of all``, so a
stale target never makes a follower faster than if it were fresh — and at what it alone
asks for; a predecessor heard before but now older than ``stop_after_s`` stops the
follower. Loss-free, this is the paper's σ with the nearest-predecessor cap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated

import numpy as np

from openconvoy.core.config import Range
from openconvoy.core.controllers import (
    HeadingControlConfig,
    PIDSpeed,
    SpeedControlConfig,
    pure_pursuit,
    stanley,
)
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import LOOKAHEAD_S
from openconvoy.core.policy import make_action

if TYPE_CHECKING:
    from openconvoy.policies.batched import BatchedClassical


@dataclass(frozen=True)
class ClassicalConfig:
    """A whole classical implementation: member side (ρ, τ, σ's gaps, ladder, layout),
    controllers, speed limit (m/s) and control rate (Hz)."""

    name: str = "custom"
    description: str = ""
    member: MemberConfig = field(default_factory=MemberConfig)
    speed: SpeedControlConfig = field(default_factory=SpeedControlConfig)
    heading: HeadingControlConfig = field(default_factory=HeadingControlConfig)
    speed_limit_mps: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 5.0
    control_rate_hz: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 20.0
    rear_weight: Annotated[float, Range(0.0, 10.0)] = 0.0
    """Bidirectional (M-CACC) coupling: weight of the follower's spacing error (0 = none)."""

    def __post_init__(self) -> None:
        if self.control_rate_hz <= 0 or self.speed_limit_mps <= 0:
            raise ConfigError("control_rate_hz and speed_limit_mps must be positive")


class ClassicalPolicy:
    """Implements ``openconvoy.core.policy.Policy`` from a ClassicalConfig."""

    def __init__(self, config: ClassicalConfig) -> None:
        self.config = config
        self.layout = config.member.layout
        self._speed = PIDSpeed(config.speed, 1.0 / config.control_rate_hz)
        self._batched: BatchedClassical | None = None

    @property
    def member_config(self) -> MemberConfig:
        return self.config.member

    @property
    def control_rate_hz(self) -> float:
        return self.config.control_rate_hz

    @property
    def name(self) -> str:
        return self.config.name

    def reset(self, seed: int | None = None) -> None:
        self._speed.reset()
        self._batched = None

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        """``act`` for a batch ``(..., D)`` -> ``(..., 2)``, each row with its own
        controller state (``policies.batched``)."""
        if self._batched is None:
            from openconvoy.policies.batched import BatchedClassical

            self._batched = BatchedClassical(self.config)
        return self._batched.act_batch(observations)

    def act(self, observation: np.ndarray) -> np.ndarray:
        view = self.layout.view(observation)
        targets, lost = self._targets(view)
        if lost or not targets:
            self._speed.reset()
            return make_action(0.0, 0.0)
        own = view.own_speed
        v_ref = targets[0][0]["speed"]  # the nearest predecessor's, as in the paper
        fresh = [t for t, stale in targets if not stale]
        stale = [t for t, is_stale in targets if is_stale]
        c = self.config.speed
        speed = math.inf
        if fresh:
            error = sum(t["spacing_error"] for t in fresh) / len(fresh)
            if self.config.rear_weight > 0.0:
                error -= self.config.rear_weight * self._rear_error(view, fresh[0]["desired_gap"])
            # The spacing error grows at the speed difference along the path.
            speed = self._speed(error, v_ref, v_ref - own)
            # Never faster than the nearest fresh predecessor alone asks.
            near = fresh[0]
            speed = min(
                speed, near["speed"] + c.kp * near["spacing_error"] + c.kd * (near["speed"] - own)
            )
        else:
            self._speed.reset()
        for t in stale:
            # Each stale target caps the speed at its term of the mean (so leaving it out
            # of the mean cannot speed the follower up) and at what it alone asks.
            e = t["spacing_error"]
            speed = min(
                speed,
                v_ref + c.kp * e + c.kd * (v_ref - own),
                t["speed"] + c.kp * e + c.kd * (t["speed"] - own),
            )
        speed = min(max(speed, 0.0), self.config.speed_limit_mps)
        return make_action(speed, self._heading_change(view.path, own))

    def _targets(self, view) -> tuple[list[tuple[dict[str, float], bool]], bool]:
        """Valid targets nearest first, each with whether it is stale (older than
        ``MemberConfig.fresh_age_s``), and whether a predecessor heard before is now too
        old to be a target (lost)."""
        degrade = self.config.member.fresh_age_s
        out: list[tuple[dict[str, float], bool]] = []
        lost = False
        for name in (*self.layout.targets[1:], "leader"):
            newest = view.states(name)[0]
            target = view.target(name)
            if target["valid"] > 0.5:
                out.append((target, bool(newest[5] > degrade)))
            elif newest[6] > 0.5 and (name != "leader" or not self._leader_in_preds(view, newest)):
                lost = True  # heard, but older than the stop age (the member dropped it)
        return out, lost

    def _leader_in_preds(self, view, newest: np.ndarray) -> bool:
        """The leader slot repeats a predecessor slot (a follower within M of the leader)."""
        return any(np.array_equal(newest, view.states(p)[0]) for p in self.layout.targets[1:])

    def _rear_error(self, view, desired_gap: float) -> float:
        """How much farther behind than desired the immediate follower is (m), 0 if unheard.
        Slowing a little for a lagging follower is what makes the string bidirectional."""
        newest = view.states("follower")[0]
        if newest[6] < 0.5:
            return 0.0
        return float(np.hypot(newest[0], newest[1])) - desired_gap

    def _heading_change(self, path: dict[str, float], speed: float) -> float:
        if path["valid"] < 0.5:
            return 0.0
        h = self.config.heading
        if h.kind == "stanley":
            return stanley(
                path["heading_error"], path["cross_track"], speed, h.gain, h.softening_mps
            )
        # Pure pursuit: the lookahead point nearest the configured lookahead time.
        j = int(np.argmin([abs(t - h.lookahead_s) for t in LOOKAHEAD_S]))
        return pure_pursuit(path[f"la{j}_x"], path[f"la{j}_y"])
