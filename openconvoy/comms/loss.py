"""Packet loss and latency models, shared by the simulated channel and by vehicles.

The simulator's channel applies them to every (sender, receiver) link; on a vehicle
`deploy --per` applies them to received (or sent) BSMs, as the OpenConvoy paper did to
emulate a crowded network. Randomness is injected: every model draws from the
``numpy.random.Generator`` given to ``reset``.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from openconvoy.core.errors import ConfigError

_MASK = (1 << 64) - 1
# SplitMix64's constants and the 53-bit unit of a uniform draw: the counter-based draws'
# definition, public because the batched kernels (envs.vector) compute the same draws.
SPLITMIX_GOLDEN = 0x9E3779B97F4A7C15
SPLITMIX_M1 = 0xBF58476D1CE4E5B9
SPLITMIX_M2 = 0x94D049BB133111EB
UNIT_53 = 2.0**-53


def _mix(z: int) -> int:
    """SplitMix64's finalizer on a 64-bit integer."""
    z = ((z ^ (z >> 30)) * SPLITMIX_M1) & _MASK
    z = ((z ^ (z >> 27)) * SPLITMIX_M2) & _MASK
    return z ^ (z >> 31)


def counter_uniform(key: int, *words: int) -> float:
    """A uniform draw in [0, 1) that depends only on ``key`` and ``words`` (counter-based).

    The channel keys its draws by (convoy seed, sender, receiver, message number) so a
    link's draws do not depend on the order the simulator visits links in: the batched
    simulator (``envs.vector.env``) makes the same draws with ``counter_uniform_array``.
    """
    z = key & _MASK
    for w in words:
        z = _mix((z + SPLITMIX_GOLDEN + (int(w) & _MASK)) & _MASK)
    return (z >> 11) * UNIT_53


def counter_state(key: int, *words: int) -> int:
    """The 64-bit state ``counter_uniform`` reaches after ``words``, to go on from with
    ``counter_uniform_from`` (or as ``counter_uniform_array``'s key): a caller drawing
    for every message of a link hashes the link's words once.
    ``counter_uniform(k, *a, *b) == counter_uniform_from(counter_state(k, *a), *b)``."""
    z = key & _MASK
    for w in words:
        z = _mix((z + SPLITMIX_GOLDEN + (int(w) & _MASK)) & _MASK)
    return z


def counter_uniform_from(state: int, *words: int) -> float:
    """``counter_uniform`` continued from ``counter_state``'s ``state``."""
    return (counter_state(state, *words) >> 11) * UNIT_53


def _mix_array(z: np.ndarray) -> np.ndarray:
    z = (z ^ (z >> np.uint64(30))) * np.uint64(SPLITMIX_M1)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(SPLITMIX_M2)
    return z ^ (z >> np.uint64(31))


def counter_state_array(key: np.ndarray | int, *words: np.ndarray | int) -> np.ndarray:
    """``counter_state`` on arrays (broadcast together), uint64: bit-identical states (a
    channel hashes every link's words at once)."""
    with np.errstate(over="ignore"):
        z = np.asarray(key, dtype=np.uint64)
        for w in words:
            z = _mix_array(z + np.uint64(SPLITMIX_GOLDEN) + np.asarray(w).astype(np.uint64))
    return z


def counter_uniform_array(key: np.ndarray | int, *words: np.ndarray | int) -> np.ndarray:
    """``counter_uniform`` on arrays (broadcast together): bit-identical draws."""
    z = counter_state_array(key, *words)
    return (z >> np.uint64(11)).astype(np.float64) * UNIT_53


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
    the message by the rest, so a message's age at first use is the drawn delay.

    ``stamp_error_s`` + ``stamp_drift`` x t (s, at send time t): how far the senders' clocks
    run behind, so every message claims to be that much older than it is and receivers
    dead-reckon it too far (the vehicle runs' own clock error: a loaded SITL host whose
    autopilot clocks fell behind 4 ms/s, shared/sitl/convoy vx-fixed-per0.3)."""

    base_s: float = 0.0
    jitter_s: float = 0.0
    samples_s: tuple[float, ...] = ()
    stamp_error_s: float = 0.0
    stamp_drift: float = 0.0

    @property
    def instant(self) -> bool:
        """Whether every message arrives when it is sent, stamped true."""
        return (
            self.base_s <= 0.0
            and self.jitter_s <= 0.0
            and not any(self.samples_s)
            and not self.stamped_off
        )

    @property
    def stamped_off(self) -> bool:
        """Whether messages carry a clock error."""
        return self.stamp_error_s != 0.0 or self.stamp_drift != 0.0

    def stamp_error(self, t: float) -> float:
        """The senders' clock error (s) at send time ``t`` (s)."""
        return self.stamp_error_s + self.stamp_drift * t

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
class LossReplay:
    """One link's recorded losses: the send times (s, sorted) of the broadcasts it dropped on
    a vehicle run. A broadcast sent at ``t`` is lost when one of them lies within
    ``window_s`` of ``t`` (half the senders' broadcast period: the nearest recorded
    broadcast decides, whatever the phase between the run's and the sim's ticks)."""

    lost_s: tuple[float, ...]
    window_s: float

    def lost(self, t: float) -> bool:
        """Whether the broadcast sent at ``t`` (s) was dropped on the run."""
        k = bisect.bisect_left(self.lost_s, t - self.window_s)
        return k < len(self.lost_s) and self.lost_s[k] < t + self.window_s


@dataclass(frozen=True)
class LossConfig:
    """Typed description of a link's loss and latency, as written in configs.

    ``model`` is ``"bernoulli"`` or ``"gilbert-elliott"``; ``mean_burst_s`` applies to
    the latter. ``latency_samples_s``: an empirical delay distribution (quantiles, s) that
    replaces the uniform jitter (``Latency``); sorted on construction. ``stamp_error_s``,
    ``stamp_drift``: the senders' clock error (``Latency``). ``link_latency_s``: per link
    ``[sender, receiver, quantile, ...]``, that link's own delay distribution (the others
    keep the common one): on vehicles each link's delay is the phase between two loops.
    ``staleness_s``: per sender (by vehicle index), how much older than the simulated state
    its messages are stamped (s). On a vehicle a message carries the autopilot's last
    telemetry sample, stamped when the autopilot took it: it is that sample's age (the
    telemetry's staleness) old when it leaves. A fitted plant already holds the staleness
    in its loop delay (its state lags the command as the logged state did), so adding it
    to the link's delay as well would make the news later than on the vehicle; instead
    the sender's messages leave with the link's delay and are stamped that much older
    (``Latency.stamp_error_s`` of the sender's links; ``fit-plant`` fits both).
    ``lost_s``: per link ``[sender, receiver, t, ...]``, the send times (s, from the
    scenario's start) of the broadcasts that link dropped on a vehicle run: the link
    replays them (drops a broadcast sent within ``lost_window_s`` of one, delivers the
    rest) in place of drawing its losses, so a sim reproduces that run's losses rather
    than another draw (``fit-plant``; ``LossReplay``). Scalar channel only.
    """

    per: float = 0.0
    model: str = "bernoulli"
    mean_burst_s: float = 1.0
    latency_s: float = 0.0
    jitter_s: float = 0.0
    latency_samples_s: tuple[float, ...] = ()
    stamp_error_s: float = 0.0
    stamp_drift: float = 0.0
    link_latency_s: tuple[tuple[float, ...], ...] = ()
    staleness_s: tuple[float, ...] = ()
    lost_s: tuple[tuple[float, ...], ...] = ()
    lost_window_s: float = 0.05

    def __post_init__(self) -> None:
        lost = tuple(tuple(float(v) for v in e) for e in self.lost_s)
        pairs = set()
        for e in lost:
            if (
                len(e) < 2
                or e[0] != int(e[0])
                or e[1] != int(e[1])
                or e[0] == e[1]
                or min(e[:2]) < 0
            ):
                raise ConfigError(
                    "lost_s entries are [sender, receiver, send time s, ...] with two "
                    f"different vehicle indices, got {list(e)[:4]}"
                )
            if e[:2] in pairs:
                raise ConfigError(f"lost_s: link {int(e[0])} -> {int(e[1])} given twice")
            pairs.add(e[:2])
            if any(not math.isfinite(v) for v in e[2:]):
                raise ConfigError(f"lost_s: send times must be finite seconds, got {list(e)[:4]}")
        object.__setattr__(self, "lost_s", tuple((e[0], e[1], *sorted(e[2:])) for e in lost))
        if not (math.isfinite(self.lost_window_s) and 0.0 < self.lost_window_s <= 1.0):
            raise ConfigError(f"lost_window_s must be seconds in (0, 1], got {self.lost_window_s}")
        stale = tuple(float(v) for v in self.staleness_s)
        if any(not (math.isfinite(v) and 0.0 <= v <= 60.0) for v in stale):
            raise ConfigError(f"staleness_s: seconds in [0, 60] per sender, got {list(stale)}")
        object.__setattr__(self, "staleness_s", stale)
        links = tuple(tuple(float(v) for v in e) for e in self.link_latency_s)
        seen = set()
        for e in links:
            if (
                len(e) < 3
                or e[0] != int(e[0])
                or e[1] != int(e[1])
                or e[0] == e[1]
                or min(e[:2]) < 0
            ):
                raise ConfigError(
                    "link_latency_s entries are [sender, receiver, delay quantile s, ...] "
                    f"with two different vehicle indices, got {list(e)}"
                )
            if e[:2] in seen:
                raise ConfigError(f"link_latency_s: link {int(e[0])} -> {int(e[1])} given twice")
            seen.add(e[:2])
            if any(not (math.isfinite(v) and 0.0 <= v <= 60.0) for v in e[2:]):
                raise ConfigError(
                    f"link_latency_s: delays must be seconds in [0, 60], got {list(e)}"
                )
        object.__setattr__(
            self, "link_latency_s", tuple((e[0], e[1], *sorted(e[2:])) for e in links)
        )
        if not (math.isfinite(self.stamp_error_s) and abs(self.stamp_error_s) <= 60.0):
            raise ConfigError(
                f"stamp_error_s must be seconds in [-60, 60], got {self.stamp_error_s}"
            )
        if not (math.isfinite(self.stamp_drift) and abs(self.stamp_drift) <= 0.1):
            raise ConfigError(f"stamp_drift must be in [-0.1, 0.1] s/s, got {self.stamp_drift}")
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
        # The common delay model, made once: a channel asks for every link's (N² at N
        # vehicles), and the config is frozen. (Not a field: not compared or printed.)
        object.__setattr__(
            self,
            "_latency",
            Latency(
                self.latency_s,
                self.jitter_s,
                self.latency_samples_s,
                self.stamp_error_s,
                self.stamp_drift,
            ),
        )

    def make(self) -> LossModel:
        """A fresh loss model for one link."""
        if self.per == 0.0:
            return NoLoss()
        if self.model == "bernoulli":
            return Bernoulli(self.per)
        return GilbertElliott.from_per(self.per, self.mean_burst_s)

    def replay(self) -> dict[tuple[int, int], LossReplay]:
        """The links that replay a vehicle run's losses (``lost_s``), by (sender, receiver)."""
        return {
            (int(e[0]), int(e[1])): LossReplay(tuple(e[2:]), self.lost_window_s)
            for e in self.lost_s
        }

    def sender_staleness(self, sender: int) -> float:
        """How much older than the simulated state ``sender``'s messages are stamped (s):
        ``staleness_s[sender]``, 0 for a sender not listed."""
        return self.staleness_s[sender] if 0 <= sender < len(self.staleness_s) else 0.0

    def link_latency(self, sender: int, receiver: int) -> Latency:
        """The delay model of the link ``sender -> receiver`` (``link_latency_s`` or the
        common one), its stamps older by the sender's staleness (``staleness_s``)."""
        base = self.latency
        stamp = base.stamp_error_s + self.sender_staleness(sender)
        if not self.link_latency_s and stamp == base.stamp_error_s:
            return base  # the common model, built once
        for e in self.link_latency_s:
            if int(e[0]) == sender and int(e[1]) == receiver:
                return Latency(base.base_s, 0.0, tuple(e[2:]), stamp, base.stamp_drift)
        return (
            base if stamp == base.stamp_error_s else dataclasses.replace(base, stamp_error_s=stamp)
        )

    @property
    def latency(self) -> Latency:
        """The common delay model of the links (one object: ``Latency`` is frozen)."""
        latency: Latency = self.__dict__["_latency"]
        return latency


def as_loss_config(loss: LossConfig | float | None = None, per: float | None = None) -> LossConfig:
    """The links' ``LossConfig`` from what an environment takes: ``loss`` a ``LossConfig``,
    a packet error rate (Bernoulli) or None (perfect links), and ``per`` a packet error
    rate in [0, 1] replacing the config's (so ``ConvoyEnv(per=0.2)`` and
    ``ConvoyEnv(loss=0.2)`` are the same convoy)."""
    if isinstance(loss, bool) or not (loss is None or isinstance(loss, (LossConfig, int, float))):
        raise ConfigError(
            f"loss must be a LossConfig or a packet error rate, got {type(loss).__name__}"
        )
    if isinstance(loss, (int, float)):
        if per is not None:
            raise ConfigError("give the packet error rate once: per=... or loss=..., not both")
        per = float(loss)
        loss = None
    config = loss or LossConfig()
    if per is None:
        return config
    if isinstance(per, bool) or not isinstance(per, (int, float)):
        raise ConfigError(f"per must be a number in [0, 1], got {type(per).__name__}")
    return dataclasses.replace(config, per=float(per))
