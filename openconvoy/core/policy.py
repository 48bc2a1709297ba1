"""The Policy protocol: the one interface classical, learned and plug-in controllers share.

A policy maps an observation (``ObservationLayout`` array) to an action
``[speed_mps, heading_change_rad]`` in SI units: the speed setpoint and the heading
setpoint as an offset from the current heading, within ±π/2. It cannot tell the simulator
from a vehicle.

What is called when (every world: ``sim``, sweeps, ``tune``, ``deploy``, ``demo``):

1. once, at load: the class (or factory) with its keyword arguments (the policy TOML's
   ``[policy.args]`` or ``--policy-arg key=value``); then ``member_config``,
   ``control_rate_hz`` and ``name`` are read (all three optional for a plug-in:
   ``policies.plugin`` supplies the scenario's member side, 20 Hz and the spec);
2. each follower gets its own deep copy; ``reset(seed)`` before each run (optional);
3. every control period (``1 / control_rate_hz`` s), for each follower:
   ``act(observation)`` with the member's observation, a float32 array of the layout
   of ``member_config`` (``member_config.layout``; ``ObservationLayout.view`` reads it
   by name: ``states(slot)`` — the last ``k`` messages of ``leader``, ``pred_1`` ..
   ``pred_M``, ``follower``, newest first, each ``dx, dy`` (m, ego frame: x forward, y
   left), ``dheading`` (rad), ``speed`` (m/s), ``accel`` (m/s²), ``age`` (s), ``valid``;
   ``own`` — ``speed``, ``accel``, ``yaw_rate``; ``target(name)`` /
   ``valid_targets()`` — ``arc_gap``, ``desired_gap`` (σ's, m), ``spacing_error`` (m,
   positive = too far behind), ``speed``, ``valid``; ``path`` — ``cross_track`` (m),
   ``heading_error`` (rad), lookahead points 0.5, 1, 2 s ahead (m, ego frame), ``valid``);
   it returns ``[speed_mps, heading_change_rad]``;
4. optionally ``act_batch(observations)`` instead of ``act`` on the batched path:
   ``(..., D) -> (..., 2)``, each row its own vehicle (``BatchPolicy``); it is run only
   after it matched ``act`` bit for bit on a test episode.

What the platform enforces on whatever ``act`` returns (``core.tick.decide``): an action
that is not two numbers, or is NaN or infinite, or an ``act`` that raises, is a policy
error: counted, and that follower stops for the rest of the run (on a vehicle: a latched
stop; the reason is ``TypeName: message`` for an exception); an ``act`` slower than the control period ``LATE_ACTS`` times in a row is a
policy error too (``ActGuard``). A good action is clipped to the action space, then the
staleness ladder and the braking rule may lower it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from openconvoy.core.errors import ConfigError

if TYPE_CHECKING:
    from openconvoy.core.member import MemberConfig

MAX_HEADING_CHANGE_RAD = math.pi / 2


@runtime_checkable
class Policy(Protocol):
    def reset(self, seed: int | None = None) -> None:
        """Forget internal state (controller memories) before a new run (``seed``: the
        run's seed, for a policy that draws random numbers)."""

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The action for one observation (float32, ``member_config.layout``), called
        once per control period: ``[speed_mps, heading_change_rad]``, SI units."""


@runtime_checkable
class ConvoyPolicy(Policy, Protocol):
    """A policy as the worlds run it (``policies.load_policy`` returns one): what its
    callers read besides ``act``. ``member_config``: the member side it was built or
    trained for (None: the scenario's, ``member.member_config_for``); ``control_rate_hz``:
    the rate it ticks at (Hz); ``name``: for logs and metadata."""

    @property
    def member_config(self) -> MemberConfig | None:
        """ρ, τ, σ's gaps, the ladder and the layout (M, k) the member runs for this
        policy; None: the scenario's (``member.member_config_for``)."""

    @property
    def control_rate_hz(self) -> float:
        """How often ``act`` is called (Hz): 20 for the presets."""

    @property
    def name(self) -> str:
        """For logs and metadata."""


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


@dataclass(frozen=True, slots=True)
class PolicyFailure:
    """What stands in for an action when ``act`` raised or was too slow (``ActGuard``):
    ``core.tick.decide`` turns it into a stop naming ``reason``."""

    reason: str


LATE_ACTS = 3
"""An ``act`` that takes longer than the control period this many times in a row is a
policy error (one slow call — a page fault, a garbage collection — is not)."""


class ActGuard:
    """Calls one follower's ``policy.act`` and times it, the same in every world: an
    ``act`` that raises, or that overruns ``period_s`` (s) ``LATE_ACTS`` times in a row,
    gives a ``PolicyFailure`` instead of an action. ``clock``: seconds (injected; the
    simulator passes ``time.perf_counter``, a vehicle its runner's monotonic clock).
    ``times``: every call's duration (s), for reports. After a failure ``act`` is not
    called again: the follower stays stopped for the run (``failure`` says why), as the
    simulator and the vehicle's failsafes latch a policy error."""

    def __init__(
        self,
        policy: Policy,
        period_s: float,
        clock: Callable[[], float] = time.perf_counter,
        late_acts: int = LATE_ACTS,
    ) -> None:
        self.policy, self.period_s, self.clock, self.late_acts = policy, period_s, clock, late_acts
        self.late = 0
        self.times: list[float] = []
        self.failure: PolicyFailure | None = None
        self.traceback = ""
        """The traceback of an ``act`` that raised ("" otherwise), for the log."""

    def __call__(self, observation: np.ndarray) -> np.ndarray | PolicyFailure:
        if self.failure is not None:
            return self.failure
        start = self.clock()
        try:
            action = self.policy.act(observation)
        except Exception as exc:  # noqa: BLE001 - the policy is foreign code: stop, report
            import traceback

            self.traceback = traceback.format_exc()
            self.failure = PolicyFailure(f"{type(exc).__name__}: {exc}")
            return self.failure
        took = self.clock() - start
        self.times.append(took)
        shape = np.shape(action)
        if shape != (2,):  # the tick's own words (``core.tick.decide``): a policy error
            self.failure = PolicyFailure(
                f"action has shape {shape}, not (2,): [speed_mps, heading_change_rad]"
            )
            return self.failure
        self.late = self.late + 1 if took > self.period_s else 0
        if self.late >= self.late_acts:
            self.failure = PolicyFailure(
                f"act took {took * 1e3:.0f} ms, over the {self.period_s * 1e3:.0f} ms control "
                f"period {self.late} times in a row"
            )
            return self.failure
        return action


def act_time_report(times: list[float], period_s: float) -> str:
    """One line on ``act``'s durations (s) against the control period (s): median, 99th
    percentile and maximum in ms, and a warning when the 99th percentile passes half of it."""
    if not times:
        return "policy act: not called"
    ms = np.array(times) * 1e3
    p50, p99, top = (float(v) for v in (np.median(ms), np.percentile(ms, 99), ms.max()))
    line = (
        f"policy act: median {p50:.2f} ms, p99 {p99:.2f} ms, max {top:.2f} ms over {len(ms)} calls"
    )
    if p99 > 0.5 * period_s * 1e3:
        line += f"; threatens the {period_s * 1e3:.0f} ms control period"
    return line


def make_action(speed_mps: float, heading_change_rad: float) -> np.ndarray:
    """An action array with the heading change clipped to ±π/2."""
    h = min(max(heading_change_rad, -MAX_HEADING_CHANGE_RAD), MAX_HEADING_CHANGE_RAD)
    return np.array([speed_mps, h], dtype=np.float32)
