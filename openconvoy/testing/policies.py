"""A policy for tests of the runner and the links: the same action every tick."""

from __future__ import annotations

import numpy as np

from openconvoy.core.member import MemberConfig
from openconvoy.core.policy import make_action
from openconvoy.testing.clock import FakeClock


class FixedPolicy:
    """Always the action ``[speed, change]`` (m/s, rad); counts its calls; on call number
    ``slow_call`` moves ``clock`` on by ``slow_s`` seconds (a policy that overruns its tick).
    Its member configuration is the ``paper`` preset's, its rate 20 Hz."""

    def __init__(
        self,
        speed: float,
        change: float,
        clock: FakeClock | None = None,
        slow_call: int = -1,
        slow_s: float = 0.0,
    ) -> None:
        from openconvoy.policies.presets import PRESETS

        self.action = make_action(speed, change)
        self.member_config: MemberConfig = PRESETS["paper"].member
        self.control_rate_hz = 20.0
        self.name = "fixed"
        self.calls = 0
        self.clock, self.slow_call, self.slow_s = clock, slow_call, slow_s

    def reset(self, seed: int | None = None) -> None:
        """Nothing to forget."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The fixed action, whatever ``obs`` says."""
        self.calls += 1
        if self.calls == self.slow_call and self.clock is not None:
            self.clock.t += self.slow_s
        return self.action


__all__ = ["FixedPolicy"]
