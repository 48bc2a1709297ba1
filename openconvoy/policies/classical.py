"""The classical policy: σ, χ_v and χ_θ composed, reading the observation's named view.

σ, read along the path: each kept predecessor ``j`` asks for the ego to sit at the point
on ``j``'s trail at the desired distance behind it; the sum of squared distances between
those points and the ego's position one step ahead is smallest at their mean, so the
target lies ``mean_j(spacing_error_j)`` metres ahead along the path (the paper's sum of
distances, with squares so the argmin is unique for two predecessors). χ_v turns that
error plus the nearest predecessor's speed into a speed setpoint; χ_θ steers onto the
nearest predecessor's trail.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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


@dataclass(frozen=True)
class ClassicalConfig:
    """A whole classical implementation: member side (ρ, τ, σ's gaps, ladder, layout),
    controllers, speed limit (m/s) and control rate (Hz)."""

    name: str = "custom"
    description: str = ""
    member: MemberConfig = field(default_factory=MemberConfig)
    speed: SpeedControlConfig = field(default_factory=SpeedControlConfig)
    heading: HeadingControlConfig = field(default_factory=HeadingControlConfig)
    speed_limit_mps: float = 5.0
    control_rate_hz: float = 20.0
    rear_weight: float = 0.0
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

    def act(self, observation: np.ndarray) -> np.ndarray:
        view = self.layout.view(observation)
        targets = view.valid_targets()
        if not targets:
            self._speed.reset()
            return make_action(0.0, 0.0)
        error = sum(t["spacing_error"] for t in targets) / len(targets)
        if self.config.rear_weight > 0.0:
            error -= self.config.rear_weight * self._rear_error(view, targets[0]["desired_gap"])
        v_ref = targets[0]["speed"]
        # The spacing error grows at the speed difference along the path.
        speed = self._speed(error, v_ref, v_ref - view.own_speed)
        speed = min(max(speed, 0.0), self.config.speed_limit_mps)
        return make_action(speed, self._heading_change(view.path, view.own_speed))

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
            return stanley(path["heading_error"], path["cross_track"], speed, h.gain, h.softening_mps)
        # Pure pursuit: the lookahead point nearest the configured lookahead time.
        j = int(np.argmin([abs(t - h.lookahead_s) for t in LOOKAHEAD_S]))
        return pure_pursuit(path[f"la{j}_x"], path[f"la{j}_y"])
