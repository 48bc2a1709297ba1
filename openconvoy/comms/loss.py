"""Packet loss and latency models, shared by the simulated channel and by vehicles.

The simulator's channel applies them to every (sender, receiver) link; on a vehicle
`deploy --per` applies them to received (or sent) BSMs, as the OpenConvoy paper did to
emulate a crowded network. Randomness is injected: every model draws from the
``numpy.random.Generator`` given to ``reset``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from openconvoy.core.errors import ConfigError

_MASK = (1 << 64) - 1
_GOLDEN = 0x9E3779B97F4A7C15
_M1 = 0xBF58476D1CE4E5B9
_M2 = 0x94D049BB133111EB
_UNIT = 2.0**-53


def _mix(z: int) -> int:
    """SplitMix64's finalizer on a 64-bit integer."""
    z = ((z ^ (z >> 30)) * _M1) & _MASK
    z = ((z ^ (z >> 27)) * _M2) & _MASK
    return z ^ (z >> 31)


def counter_uniform(key: int, *words: int) -> float:
    """A uniform draw in [0, 1) that depends only on ``key`` and ``words`` (counter-based).

    The channel keys its draws by (convoy seed, sender, receiver, message number) so a
    link's draws do not depend on the order the simulator visits links in: the batched
    simulator (``envs.vector.env``) makes the same draws with ``counter_uniform_array``.
    """
    z = key & _MASK
    for w in words:
        z = _mix((z + _GOLDEN + (int(w) & _MASK)) & _MASK)
    return (z >> 11) * _UNIT


def counter_state(key: int, *words: int) -> int:
    """The 64-bit state ``counter_uniform`` reaches after ``words``, to go on from with
    ``counter_uniform_from`` (or as ``counter_uniform_array``'s key): a caller drawing
    for every message of a link hashes the link's words once.
    ``counter_uniform(k, *a, *b) == counter_uniform_from(counter_state(k, *a), *b)``."""
    z = key & _MASK
    for w in words:
        z = _mix((z + _GOLDEN + (int(w) & _MASK)) & _MASK)
    return z


def counter_uniform_from(state: int, *words: int) -> float:
    """``counter_uniform`` continued from ``counter_state``'s ``state``."""
    return (counter_state(state, *words) >> 11) * _UNIT


def _mix_array(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * np.uint64(_M1)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(_M2)
    return z ^ (z >> np.uint64(31))


def counter_uniform_array(key: np.ndarray | int, *words: np.ndarray | int) -> np.ndarray:
    """``counter_uniform`` on arrays (broadcast together): bit-identical draws."""
    with np.errstate(over="ignore"):
        z = np.asarray(key, dtype=np.uint64)
        for w in words:
            z = _mix_array(z + np.uint64(_GOLDEN) + np.asarray(w).astype(np.uint64))
    return (z >> np.uint64(11)).astype(np.float64) * _UNIT


class LossModel(Protocol):
    """Decides, packet by packet, whether a message is lost."""

    def reset(self, rng: np.random.Generator) -> None:
        """Start over with a new random source."""

    def lost(self, t: float) -> bool:
        """True when a packet offered at time ``t`` (seconds, non-decreasing) is dropped."""


class NoLoss:
    """A perfect link."""

    def reset(self, rng: np.random.Generator) -> None:
        pass

    def lost(self, t: float) -> bool:
        return False


class Bernoulli:
    """Independent loss with packet error rate ``per`` (0..1)."""

    def __init__(self, per: float) -> None:
        if not 0.0 <= per <= 1.0:
            raise ConfigError(f"packet error rate must be in [0, 1], got {per}")
        self.per = per
        self._rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng

    def lost(self, t: float) -> bool:
        return self.per > 0.0 and self._rng.random() < self.per


GE_INIT, GE_ADVANCE, GE_LOSS = 0, 1, 2
"""Purpose words of the Gilbert-Elliott chain's counter-based draws (the initial state,
then per packet the state transition and the loss)."""


class GilbertElliott:
    """Bursty loss: a two-state (good/bad) Markov chain evolving in continuous time.

    The link spends exponentially distributed sojourns in each state, with means
    ``mean_good_s`` and ``mean_bad_s``; a packet is lost with probability ``loss_good``
    in the good state and ``loss_bad`` in the bad state. Time-based (not packet-based)
    so the burst length in seconds does not depend on the message rate.
    """

    def __init__(
        self,
        mean_good_s: float,
        mean_bad_s: float,
        loss_good: float = 0.0,
        loss_bad: float = 1.0,
    ) -> None:
        if mean_good_s <= 0 or mean_bad_s <= 0:
            raise ConfigError("Gilbert-Elliott sojourn times must be positive")
        self.mean_good_s = mean_good_s
        self.mean_bad_s = mean_bad_s
        self.loss_good = loss_good
        self.loss_bad = loss_bad
        self.reset(np.random.default_rng(0))

    @classmethod
    def from_per(cls, per: float, mean_burst_s: float) -> GilbertElliott:
        """The chain whose long-run loss rate is ``per`` with bursts of ``mean_burst_s``."""
        if not 0.0 < per < 1.0:
            if per == 0.0:
                return cls(mean_good_s=1e12, mean_bad_s=mean_burst_s)
            raise ConfigError(f"packet error rate must be in [0, 1), got {per}")
        return cls(mean_good_s=mean_burst_s * (1.0 - per) / per, mean_bad_s=mean_burst_s)

    @property
    def per(self) -> float:
        """Long-run packet error rate."""
        p_bad = self.mean_bad_s / (self.mean_good_s + self.mean_bad_s)
        return p_bad * self.loss_bad + (1.0 - p_bad) * self.loss_good

    def reset(self, rng: np.random.Generator) -> None:
        # Counter-based draws keyed by one number from rng: packet n's draws are
        # ``counter_uniform(key, n, GE_ADVANCE | GE_LOSS)``, so the batched simulator
        # (``envs.vector.env``) can make them for every link at once.
        self.key = int(rng.integers(2**63))
        self._n = 0
        p_bad = self.mean_bad_s / (self.mean_good_s + self.mean_bad_s)
        self._bad = bool(counter_uniform(self.key, GE_INIT) < p_bad)
        self._t: float | None = None

    def lost(self, t: float) -> bool:
        n = self._n
        self._n += 1
        if self._t is not None and t > self._t:
            self._advance(t - self._t, n)
        self._t = t if self._t is None else max(self._t, t)
        p = self.loss_bad if self._bad else self.loss_good
        return p > 0.0 and counter_uniform(self.key, n, GE_LOSS) < p

    def _advance(self, dt: float, n: int) -> None:
        # Exact two-state transition over dt: relaxes towards the stationary law.
        a = 1.0 / self.mean_good_s  # good -> bad rate
        b = 1.0 / self.mean_bad_s  # bad -> good rate
        p_bad_inf = a / (a + b)
        decay = math.exp(-(a + b) * dt)
        start = 1.0 if self._bad else 0.0
        p_bad = p_bad_inf + (start - p_bad_inf) * decay
        self._bad = bool(counter_uniform(self.key, n, GE_ADVANCE) < p_bad)


def quantile_delay(samples: tuple[float, ...] | list[float], u: float) -> float:
    """The delay (s) at probability ``u`` in [0, 1) of the empirical distribution whose
    sorted quantiles at probabilities 0, 1/(n-1), ..., 1 are ``samples``: linear between
    neighbours (the inverse of a piecewise-linear CDF; ``envs.vector.channel`` compiles the
    same arithmetic)."""
    n = len(samples)
    if n == 1:
        return float(samples[0])
    pos = u * (n - 1)
    k = int(pos)
    if k >= n - 1:
        return float(samples[n - 1])
    return samples[k] + (pos - k) * (samples[k + 1] - samples[k])


@dataclass(frozen=True)
class Latency:
    """Delivery delay, seconds: ``base_s`` plus either a uniform jitter in [0, ``jitter_s``]
    or, when ``samples_s`` is given, a draw from that empirical distribution (sorted
    quantiles, as ``fit-plant`` fits from a vehicle run's message ages; ``quantile_delay``).
    The delay is continuous: the simulated channel delivers at the next tick and advances
    the message by the rest, so a message's age at first use is the drawn delay."""

    base_s: float = 0.0
    jitter_s: float = 0.0
    samples_s: tuple[float, ...] = ()

    @property
    def instant(self) -> bool:
        """Whether every message arrives when it is sent."""
        return self.base_s <= 0.0 and self.jitter_s <= 0.0 and not any(self.samples_s)

    @property
    def max_s(self) -> float:
        """The longest delay a message can get (s)."""
        return self.base_s + (max(self.samples_s) if self.samples_s else self.jitter_s)

    def from_uniform(self, u: float) -> float:
        """The delay (s) for a uniform draw ``u`` in [0, 1)."""
        if self.samples_s:
            return self.base_s + quantile_delay(self.samples_s, u)
        return self.base_s + u * self.jitter_s

    def delay(self, rng: np.random.Generator) -> float:
        """Draw one packet's delay, seconds."""
        if self.jitter_s <= 0.0 and not self.samples_s:
            return self.base_s
        return self.from_uniform(float(rng.random()))


@dataclass(frozen=True)
class LossConfig:
    """Typed description of a link's loss and latency, as written in configs.

    ``model`` is ``"bernoulli"`` or ``"gilbert-elliott"``; ``mean_burst_s`` applies to
    the latter. ``latency_samples_s``: an empirical delay distribution (quantiles, s) that
    replaces the uniform jitter (``Latency``); sorted on construction.
    """

    per: float = 0.0
    model: str = "bernoulli"
    mean_burst_s: float = 1.0
    latency_s: float = 0.0
    jitter_s: float = 0.0
    latency_samples_s: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.model not in ("bernoulli", "gilbert-elliott"):
            raise ConfigError(
                f"unknown loss model {self.model!r} (expected 'bernoulli' or 'gilbert-elliott')"
            )
        if not 0.0 <= self.per <= 1.0:
            raise ConfigError(f"per must be in [0, 1], got {self.per}")
        samples = tuple(float(v) for v in self.latency_samples_s)
        if any(not (math.isfinite(v) and 0.0 <= v <= 60.0) for v in samples):
            raise ConfigError(
                f"latency samples must be seconds in [0, 60], got {list(self.latency_samples_s)}"
            )
        if samples and self.jitter_s > 0.0:
            raise ConfigError("give either a latency jitter or latency samples, not both")
        object.__setattr__(self, "latency_samples_s", tuple(sorted(samples)))

    def make(self) -> LossModel:
        """A fresh loss model for one link."""
        if self.per == 0.0:
            return NoLoss()
        if self.model == "bernoulli":
            return Bernoulli(self.per)
        return GilbertElliott.from_per(self.per, self.mean_burst_s)

    @property
    def latency(self) -> Latency:
        return Latency(self.latency_s, self.jitter_s, self.latency_samples_s)
