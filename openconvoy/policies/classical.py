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
    clamp,
    pd_speed,
    pure_pursuit,
    stanley,
)
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import MemberConfig
from openconvoy.core.mpc import MPCConfig
from openconvoy.core.observation import (
    DERIVED_FEATURES,
    LOOKAHEAD_S,
    PATH_FEATURES,
    STATE_FEATURES,
)
from openconvoy.core.policy import make_action

if TYPE_CHECKING:
    from openconvoy.policies.batched import BatchedClassical

_NF, _ND = len(STATE_FEATURES), len(DERIVED_FEATURES)
_AGE, _HEARD = STATE_FEATURES.index("age"), STATE_FEATURES.index("valid")
_DESIRED, _ERROR = DERIVED_FEATURES.index("desired_gap"), DERIVED_FEATURES.index("spacing_error")
_SPEED, _VALID = DERIVED_FEATURES.index("speed"), DERIVED_FEATURES.index("valid")
_PATH_VALID = PATH_FEATURES.index("valid")


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
    mpc: MPCConfig | None = None
    """The ``mpc`` controller family (``policies.mpc``) in place of χ_v when set; ``speed``
    is then its fallback when a solve fails."""

    def __post_init__(self) -> None:
        if self.control_rate_hz <= 0 or self.speed_limit_mps <= 0:
            raise ConfigError("control_rate_hz and speed_limit_mps must be positive")


def lookahead_index(heading: HeadingControlConfig) -> int:
    """Pure pursuit's lookahead point: the index into ``LOOKAHEAD_S`` of the time nearest
    the configured lookahead time (the first of two as near)."""
    return int(np.argmin([abs(t - heading.lookahead_s) for t in LOOKAHEAD_S]))


class ClassicalPolicy:
    """Implements ``openconvoy.core.policy.Policy`` from a ClassicalConfig."""

    def __init__(self, config: ClassicalConfig) -> None:
        self.config = config
        self.layout = config.member.layout
        dt = 1.0 / config.control_rate_hz
        self._speed_plugin = config.speed.plugin(dt) if config.speed.is_plugin else None
        self._speed = self._speed_plugin or PIDSpeed(config.speed, dt)
        self._heading_plugin = config.heading.plugin(dt) if config.heading.is_plugin else None
        self._kp, self._kd = config.speed.kp, config.speed.kd
        self._law = self._plugin_law if self._speed_plugin is not None else self._pd_law
        self._batched: BatchedClassical | None = None
        lay = self.layout
        self._target_slots = [
            (name, lay.slot_offset(name), lay.target_offset(name))
            for name in (*lay.targets[1:], "leader")
        ]
        """Nearest first: (name, offset of its newest state, offset of its derived features)."""
        self._pred_states = [lay.slot_offset(p) for p in lay.targets[1:]]
        self._stale_limits: dict[np.dtype, float] = {}
        self._lookahead = lookahead_index(config.heading)

    @property
    def member_config(self) -> MemberConfig:
        return self.config.member

    @property
    def control_rate_hz(self) -> float:
        return self.config.control_rate_hz

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def plugins(self) -> list[str]:
        """Every plug-in component of this policy, as ``"spacing module:Name"``."""
        c = self.config
        out = list(c.member.plugins)
        out += [f"speed controller {c.speed.kind}"] if c.speed.is_plugin else []
        return out + ([f"heading controller {c.heading.kind}"] if c.heading.is_plugin else [])

    def reset(self, seed: int | None = None) -> None:
        self._reset_speed()
        if self._heading_plugin is not None and callable(
            getattr(self._heading_plugin, "reset", None)
        ):
            self._heading_plugin.reset()
        self._batched = None

    def _reset_speed(self) -> None:
        if self._speed_plugin is None or callable(getattr(self._speed_plugin, "reset", None)):
            self._speed.reset()

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        """``act`` for a batch ``(..., D)`` -> ``(..., 2)``, each row with its own
        controller state (``policies.batched``)."""
        if self._batched is None:
            from openconvoy.policies.batched import BatchedClassical

            self._batched = BatchedClassical(self.config)
        return self._batched.act_batch(observations)

    def reset_rows(self, rows: np.ndarray) -> None:
        """Forget the batched controller state of the rows where ``rows`` (bool, the batch
        shape of ``act_batch``) is True: convoys that started a new episode."""
        if self._batched is not None:
            self._batched.reset_rows(rows)

    def act(self, observation: np.ndarray) -> np.ndarray:
        lay = self.layout
        if observation.shape != (lay.size,):
            raise ValueError(
                f"observation has shape {observation.shape}, layout expects ({lay.size},)"
            )
        obs = observation.tolist()  # plain floats: cheaper to read one by one than numpy's
        targets, lost = self._targets(obs, self._stale_after(observation.dtype))
        if lost or not targets:
            self._reset_speed()
            return make_action(0.0, 0.0)
        own = obs[lay.own_offset]
        v_ref = targets[0][0][_SPEED]  # the nearest predecessor's, as in the paper
        fresh = [t for t, stale in targets if not stale]
        stale = [t for t, is_stale in targets if is_stale]
        speed = math.inf
        law = self._law  # χ_v's law on one target alone (a cap)
        if fresh:
            error = sum(t[_ERROR] for t in fresh) / len(fresh)
            if self.config.rear_weight > 0.0:
                error -= self.config.rear_weight * self._rear_error(observation, fresh[0][_DESIRED])
            # The spacing error grows at the speed difference along the path.
            speed = self._speed(error, v_ref, v_ref - own)
            # Never faster than the nearest fresh predecessor alone asks.
            near = fresh[0]
            speed = min(speed, law(near[_ERROR], near[_SPEED], near[_SPEED] - own))
        else:
            self._reset_speed()
        for t in stale:
            # Each stale target caps the speed at its term of the mean (so leaving it out
            # of the mean cannot speed the follower up) and at what it alone asks.
            e = t[_ERROR]
            speed = min(
                speed,
                law(e, v_ref, v_ref - own),
                law(e, t[_SPEED], t[_SPEED] - own),
            )
        speed = clamp(speed, 0.0, self.config.speed_limit_mps)
        return make_action(speed, self._heading_change(obs, own))

    def _pd_law(self, error: float, v_ref: float, error_rate: float) -> float:
        """The built-in χ_v's law on one target (a cap): PD."""
        return pd_speed(error, v_ref, error_rate, self._kp, self._kd)

    def _plugin_law(self, error: float, v_ref: float, error_rate: float) -> float:
        """A plug-in χ_v's law on one target (a cap): its call."""
        return float(self._speed(error, v_ref, error_rate))

    def _stale_after(self, dtype: np.dtype) -> float:
        """``MemberConfig.fresh_age_s`` as an observation of ``dtype`` holds it: an age
        compares with it as numpy compares an array element with a Python float."""
        limit = self._stale_limits.get(dtype)
        if limit is None:
            fresh = self.config.member.fresh_age_s
            limit = float(dtype.type(fresh)) if dtype.kind == "f" else fresh
            self._stale_limits[dtype] = limit
        return limit

    def _targets(
        self, obs: list[float], stale_after: float
    ) -> tuple[list[tuple[list[float], bool]], bool]:
        """Valid targets nearest first (their ``DERIVED_FEATURES``), each with whether it
        is stale (its newest message older than ``MemberConfig.fresh_age_s``), and whether
        a predecessor heard before is now too old to be a target (lost)."""
        out: list[tuple[list[float], bool]] = []
        lost = False
        for name, state, target in self._target_slots:
            derived = obs[target : target + _ND]
            if derived[_VALID] > 0.5:
                out.append((derived, obs[state + _AGE] > stale_after))
            elif obs[state + _HEARD] > 0.5 and (
                name != "leader" or not self._leader_in_preds(obs, state)
            ):
                lost = True  # heard, but older than the stop age (the member dropped it)
        return out, lost

    def _leader_in_preds(self, obs: list[float], leader: int) -> bool:
        """The leader slot repeats a predecessor slot (a follower within M of the leader)."""
        newest = obs[leader : leader + _NF]
        return any(newest == obs[p : p + _NF] for p in self._pred_states)

    def _rear_error(self, observation: np.ndarray, desired_gap: float) -> float:
        """How much farther behind than desired the immediate follower is (m), 0 if unheard.
        Slowing a little for a lagging follower is what makes the string bidirectional."""
        newest = self.layout.view(observation).states("follower")[0]
        if newest[6] < 0.5:
            return 0.0
        return float(np.hypot(newest[0], newest[1])) - desired_gap

    def _heading_change(self, obs: list[float], speed: float) -> float:
        o = self.layout.path_offset
        if obs[o + _PATH_VALID] < 0.5:
            return 0.0
        h = self.config.heading
        if self._heading_plugin is not None:
            points = tuple(
                (obs[o + 2 + 2 * j], obs[o + 3 + 2 * j]) for j in range(len(LOOKAHEAD_S))
            )
            return float(self._heading_plugin(obs[o], obs[o + 1], speed, points))
        if h.kind == "stanley":
            return stanley(obs[o + 1], obs[o], speed, h.gain, h.softening_mps)
        # Pure pursuit: the lookahead point nearest the configured lookahead time.
        j = self._lookahead
        return pure_pursuit(obs[o + 2 + 2 * j], obs[o + 3 + 2 * j])
