"""The Policy protocol: the one interface classical and learned controllers share.

A policy maps an observation (``ObservationLayout`` array) to an action
``[speed_mps, heading_change_rad]`` in SI units: the speed setpoint and the heading
setpoint as an offset from the current heading, within ±π/2. It cannot tell the simulator
from a vehicle.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from openconvoy.core.errors import ConfigError

if TYPE_CHECKING:
    from openconvoy.core.member import MemberConfig

MAX_HEADING_CHANGE_RAD = math.pi / 2


@runtime_checkable
class Policy(Protocol):
    def reset(self, seed: int | None = None) -> None:
        """Forget internal state (controller memories) before a new run."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The action for one observation: ``[speed_mps, heading_change_rad]``."""


@runtime_checkable
class ConvoyPolicy(Policy, Protocol):
    """A policy as the worlds run it (``policies.load_policy`` returns one): what its
    callers read besides ``act``. ``member_config``: the member side it was built or
    trained for (None: the scenario's, ``member.member_config_for``); ``control_rate_hz``:
    the rate it ticks at (Hz); ``name``: for logs and metadata."""

    @property
    def member_config(self) -> MemberConfig | None: ...

    @property
    def control_rate_hz(self) -> float: ...

    @property
    def name(self) -> str: ...


@runtime_checkable
class BatchPolicy(Protocol):
    """A policy that also acts on many vehicles at once (the batched simulator, batched
    sweeps and training use it when a policy declares it): ``act_batch`` takes observations
    ``(..., D)`` and returns actions ``(..., 2)`` float32 in SI units (speed m/s, heading
    change rad), one row per vehicle, each row's controller memory kept apart."""

    def act_batch(self, observations: np.ndarray) -> np.ndarray: ...


CONVOY_POLICY_ATTRIBUTES = ("reset", "act", "member_config", "control_rate_hz", "name")


def as_convoy_policy(obj: Any, where: str = "policy") -> ConvoyPolicy:
    """``obj`` if it has everything ``ConvoyPolicy`` declares, else a ``ConfigError``
    naming what is missing (checked once, where a policy is loaded or handed over)."""
    missing = [a for a in CONVOY_POLICY_ATTRIBUTES if not hasattr(obj, a)]
    if missing:
        raise ConfigError(
            f"{where} ({type(obj).__name__}) lacks {', '.join(missing)}: a convoy policy "
            f"declares {', '.join(CONVOY_POLICY_ATTRIBUTES)}"
        )
    return obj


def make_action(speed_mps: float, heading_change_rad: float) -> np.ndarray:
    """An action array with the heading change clipped to ±π/2."""
    h = min(max(heading_change_rad, -MAX_HEADING_CHANGE_RAD), MAX_HEADING_CHANGE_RAD)
    return np.array([speed_mps, h], dtype=np.float32)
