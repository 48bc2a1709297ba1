"""Controllers χ_v (speed) and χ_θ (heading).

Speed controllers turn a spacing error (m, positive = too far behind) and a reference
speed (m/s, the predecessors' speed) into a speed setpoint. Heading controllers turn path
geometry in the ego frame into a heading change (rad, CCW positive). All are stateful
only through what ``reset`` clears; the time step is fixed at construction.

Either may be a plug-in (``core.plugins``) built with its ``params`` (and ``dt_s``, the
control period in seconds, where its constructor names it): a speed controller is called
``(error_m, v_ref_mps, error_rate_mps) -> speed setpoint (m/s)``, a heading controller
``(cross_track_m, heading_error_rad, speed_mps, lookahead) -> heading change (rad)``,
``lookahead`` the path points 0.5, 1 and 2 s ahead as ``((x_m, y_m), ...)`` in the ego
frame; ``reset()`` is optional (docs/your-controller.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Any

from openconvoy.core import plugins
from openconvoy.core.config import Range


@dataclass(frozen=True)
class SpeedControlConfig:
    """χ_v: ``kind`` ``pd`` or ``pid``; gains on the spacing error (1/s, 1/s², -)."""

    kind: str = "pd"
    kp: Annotated[float, Range(0.0, 100.0)] = 0.3
    ki: Annotated[float, Range(0.0, 100.0)] = 0.0
    kd: Annotated[float, Range(0.0, 100.0)] = 1.1
    integral_limit: Annotated[float, Range(0.0, 1000.0)] = 5.0
    params: dict[str, Any] = field(default_factory=dict, hash=False)
    """A plug-in's keyword arguments (its ``kind`` a plug-in reference)."""

    def __post_init__(self) -> None:
        if self.is_plugin:
            self.plugin(0.05)  # a plug-in that loads, takes ``params`` and is callable

    @property
    def is_plugin(self) -> bool:
        return self.kind not in ("pd", "pid")

    def plugin(self, dt_s: float) -> Any:
        """A new instance of the plug-in ``kind`` names, for control period ``dt_s`` (s)."""
        where = f"speed controller {self.kind!r} (built-in: pd, pid)"
        return plugins.component("speed", self.kind, self.params, where, dt_s=dt_s)


class PIDSpeed:
    """v_cmd = v_ref + kp·e + ki·∫e + kd·ė, with ė from successive errors.

    The paper's PD is the ``ki = 0`` case. The derivative of the spacing error is the
    relative speed, so kd damps closing speed; the first step after reset has no
    derivative kick.
    """

    def __init__(self, config: SpeedControlConfig, dt: float) -> None:
        self.config = config
        self.dt = dt
        self.reset()

    def reset(self) -> None:
        self._prev: float | None = None
        self._integral = 0.0

    def __call__(self, error: float, v_ref: float, error_rate: float | None = None) -> float:
        """Speed setpoint (m/s) for spacing ``error`` (m) and reference speed ``v_ref``.

        ``error_rate`` (m/s), when the caller knows it (relative speed), replaces the
        finite difference, which amplifies the jumps of message-driven errors.
        """
        c = self.config
        if error_rate is not None:
            de = error_rate
        else:
            de = 0.0 if self._prev is None else (error - self._prev) / self.dt
        self._prev = error
        if c.kind == "pid":
            self._integral = integrated(self._integral, error, self.dt, c.integral_limit)
        return speed_law(error, v_ref, de, self._integral, c.kp, c.ki, c.kd)


def speed_law(
    error: float, v_ref: float, error_rate: float, integral: float, kp: float, ki: float, kd: float
) -> float:
    """χ_v's setpoint (m/s): ``v_ref + kp·e + ki·∫e + kd·ė`` for spacing error ``error``
    (m), its rate (m/s) and integral (m·s), summed in that order."""
    return v_ref + kp * error + ki * integral + kd * error_rate


def pd_speed(error: float, v_ref: float, error_rate: float, kp: float, kd: float) -> float:
    """The PD law on one target alone (m/s), a cap: ``v_ref + kp·e + kd·ė``."""
    return v_ref + kp * error + kd * error_rate


def integrated(integral: float, error: float, dt: float, limit: float) -> float:
    """The PID integrator after one step of ``dt`` (s) on ``error`` (m), held within
    ±``limit`` (m·s)."""
    return clamp(integral + error * dt, -limit, limit)


def clamp(x: float, lo: float, hi: float) -> float:
    """``x`` held within [``lo``, ``hi``] (Python's ``min(max(x, lo), hi)``: NaN stays)."""
    return min(max(x, lo), hi)


@dataclass(frozen=True)
class HeadingControlConfig:
    """χ_θ: ``stanley`` (gain, 1/s... dimensionless on cross-track/speed) or
    ``pure-pursuit`` (lookahead time, s, with a minimum distance, m)."""

    kind: str = "stanley"
    gain: Annotated[float, Range(0.0, 100.0)] = 0.2
    softening_mps: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 0.5
    lookahead_s: Annotated[float, Range(0.0, 60.0, lo_open=True)] = 1.0
    min_lookahead_m: Annotated[float, Range(0.0, 1000.0)] = 1.0
    params: dict[str, Any] = field(default_factory=dict, hash=False)
    """A plug-in's keyword arguments (its ``kind`` a plug-in reference)."""

    def __post_init__(self) -> None:
        if self.is_plugin:
            self.plugin(0.05)  # a plug-in that loads, takes ``params`` and is callable

    @property
    def is_plugin(self) -> bool:
        return self.kind not in ("stanley", "pure-pursuit")

    def plugin(self, dt_s: float) -> Any:
        """A new instance of the plug-in ``kind`` names, for control period ``dt_s`` (s)."""
        where = f"heading controller {self.kind!r} (built-in: stanley, pure-pursuit)"
        return plugins.component("heading", self.kind, self.params, where, dt_s=dt_s)


def stanley(
    heading_error: float, cross_track: float, speed: float, gain: float, soft: float
) -> float:
    """Stanley steering law as a heading change (rad).

    ``heading_error``: path heading − ego heading (rad); ``cross_track``: path's lateral
    offset from the ego, positive when the path lies to the ego's left (m).
    """
    return heading_error + math.atan2(gain * cross_track, soft + abs(speed))


def pure_pursuit(target_x: float, target_y: float) -> float:
    """Heading change (rad) pointing at a lookahead point given in the ego frame (m)."""
    if target_x == 0.0 and target_y == 0.0:
        return 0.0
    return math.atan2(target_y, target_x)
