"""Rx gates ρ(i, j) (topologies) and Tx gates τ(R^i) (when to broadcast).

Topology names are DESIGN.md's: ``predecessor``, ``all-predecessors``, ``lookahead:K``
(``lookahead:N`` = every predecessor), ``leader``, ``leader-predecessor``,
``bidirectional``, ``all``. Vehicle 0 leads; a predecessor has a smaller id.

Either gate may be a plug-in (``core.plugins``: ``mylab.gates:Ring``, ``file.py:Name`` or
an entry point) built with its ``params``: a topology has ``keeps(ego, sender,
n_vehicles) -> bool``; a trigger ``should_send(own, last_sent, now) -> bool``, asked on the
``period_s`` grid, and optionally ``reset()`` (docs/your-controller.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from openconvoy.core import plugins
from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError
from openconvoy.core.state import VehicleState

TOPOLOGIES = (
    "predecessor",
    "all-predecessors",
    "lookahead:K",
    "leader",
    "leader-predecessor",
    "bidirectional",
    "all",
)


@dataclass(frozen=True)
class RxGate:
    """ρ: which senders' messages vehicle ``ego`` keeps, for a named topology."""

    topology: str
    ego: int
    n_vehicles: int
    params: Mapping[str, Any] = field(default_factory=dict, hash=False, compare=False)
    """A plug-in topology's keyword arguments."""

    def __post_init__(self) -> None:
        plugin = None
        if is_plugin_topology(self.topology):
            plugin = topology_plugin(self.topology, self.params)
            # Asked once for every sender of the convoy: a plug-in that raises or answers
            # something else than true or false fails here, in one line, not mid-run.
            try:
                table = [plugin.keeps(self.ego, j, self.n_vehicles) for j in range(self.n_vehicles)]
            except Exception as exc:  # noqa: BLE001 - the plug-in's code
                raise ConfigError(
                    f"topology {self.topology}: keeps({self.ego}, j, {self.n_vehicles}) raised "
                    f"{type(exc).__name__}: {exc}"
                ) from None
            if not all(isinstance(k, (bool, np.bool_)) for k in table):
                raise ConfigError(
                    f"topology {self.topology}: keeps() returned {table!r}; expected true or false"
                )
        object.__setattr__(self, "_plugin", plugin)
        _ = self.lookahead  # validates the name

    @property
    def lookahead(self) -> int | None:
        """K for ``lookahead:K`` (``N`` = all predecessors), else None."""
        name = self.topology
        if is_plugin_topology(name):
            return None
        if name.startswith("lookahead:"):
            k = name.split(":", 1)[1]
            if k == "N":
                return max(self.n_vehicles - 1, 1)
            if not k.isdigit() or int(k) < 1:
                raise ConfigError(f"bad topology {name!r}: lookahead needs a positive K or N")
            return int(k)
        if name not in TOPOLOGIES:
            raise ConfigError(f"unknown topology {name!r}; expected one of {', '.join(TOPOLOGIES)}")
        return None

    def keeps(self, sender: int) -> bool:
        """ρ(ego, sender) = 1."""
        i, j = self.ego, sender
        if j == i:
            return False
        plugin = self._plugin  # type: ignore[attr-defined]
        if plugin is not None:
            return bool(plugin.keeps(i, j, self.n_vehicles))
        t = self.topology
        if t == "all":
            return True
        if t == "predecessor":
            return j == i - 1
        if t == "all-predecessors":
            return j < i
        if t == "leader":
            return j == 0
        if t == "leader-predecessor":
            return j == 0 or j == i - 1
        if t == "bidirectional":
            return j == i - 1 or j == i + 1
        k = self.lookahead
        return k is not None and i - k <= j < i

    def kept_row(self) -> np.ndarray:
        """ρ(ego, j) for every sender ``j`` of the convoy, as a bool array of
        ``n_vehicles``: in bulk for a built-in topology (O(N) numpy, no per-sender
        call), else each sender asked through ``keeps`` (a plug-in's ``keeps``)."""
        n, i = self.n_vehicles, self.ego
        if self._plugin is not None:  # type: ignore[attr-defined]
            return np.array([self.keeps(j) for j in range(n)], dtype=bool)
        j = np.arange(n)
        t = self.topology
        if t == "all":
            row = np.ones(n, dtype=bool)
        elif t == "predecessor":
            row = j == i - 1
        elif t == "all-predecessors":
            row = j < i
        elif t == "leader":
            row = j == 0
        elif t == "leader-predecessor":
            row = (j == 0) | (j == i - 1)
        elif t == "bidirectional":
            row = (j == i - 1) | (j == i + 1)
        else:
            k = self.lookahead
            row = (i - k <= j) & (j < i) if k is not None else np.zeros(n, dtype=bool)
        row = np.asarray(row, dtype=bool)
        if 0 <= i < n:
            row[i] = False
        return row

    def needed(self) -> list[int]:
        """Vehicles whose messages the ego needs to cooperate (the staleness ladder and the
        bridge's message-age rule watch them): every predecessor the topology keeps,
        nearest first (a follower of the leader alone needs the leader). Followers behind
        are never needed: losing them cannot make the ego drive into anything. Empty for
        the leader."""
        if not 0 <= self.ego < self.n_vehicles:  # no row to read: ρ per sender
            return [j for j in range(self.ego - 1, -1, -1) if self.keeps(j)]
        row = self.kept_row()
        return [j for j in range(self.ego - 1, -1, -1) if row[j]]


def is_plugin_topology(name: str) -> bool:
    """``name`` is no built-in topology (``lookahead:K`` included): a plug-in reference."""
    return name not in TOPOLOGIES and not name.startswith("lookahead:")


def topology_plugin(name: str, params: Mapping[str, Any]) -> Any:
    """A new instance of the topology plug-in ``name`` (``core.plugins.component``)."""
    where = f"topology {name!r} (built-in: {', '.join(TOPOLOGIES)})"
    return plugins.component("topology", name, params, where)


@dataclass(frozen=True)
class TriggerConfig:
    """τ's configuration.

    ``kind``: ``periodic`` (send every ``period_s``) or ``event`` (checked every
    ``period_s``; send when the own position deviates from what the others extrapolate
    from the last message by more than ``threshold_m``, or the speed by more than
    ``speed_threshold_mps``, or after ``max_silence_s`` without sending).
    """

    kind: str = "periodic"
    period_s: Annotated[float, Range(0.0, 60.0, lo_open=True)] = 0.1
    threshold_m: Annotated[float, Range(0.0, 1000.0, lo_open=True)] = 0.5
    speed_threshold_mps: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 0.5
    max_silence_s: Annotated[float, Range(0.0, 600.0, lo_open=True)] = 1.0
    params: dict[str, Any] = field(default_factory=dict, hash=False)
    """A plug-in's keyword arguments (its ``kind`` a plug-in reference, asked every
    ``period_s``)."""

    def __post_init__(self) -> None:
        if self.period_s <= 0:
            raise ConfigError(f"trigger period_s must be positive, got {self.period_s}")
        if self.is_plugin:
            self.plugin()  # a plug-in that loads, takes ``params`` and has should_send

    @property
    def is_plugin(self) -> bool:
        return self.kind not in ("periodic", "event")

    def plugin(self) -> Any:
        """A new instance of the plug-in ``kind`` names (``core.plugins.component``)."""
        where = f"trigger {self.kind!r} (built-in: periodic, event)"
        return plugins.component("trigger", self.kind, self.params, where)


class TxGate:
    """τ: decides whether to broadcast the own state now."""

    def __init__(self, config: TriggerConfig) -> None:
        self.config = config
        self._plugin = config.plugin() if config.is_plugin else None
        self.reset()

    def reset(self) -> None:
        self._next_check = -math.inf
        self._last_sent: VehicleState | None = None
        if self._plugin is not None and callable(getattr(self._plugin, "reset", None)):
            self._plugin.reset()

    def should_send(self, own: VehicleState, now: float) -> bool:
        """True when the own state should be broadcast at ``now``; records it as sent."""
        c = self.config
        if now + 1e-9 < self._next_check:
            return False
        # Keep the check grid fixed so periodic sending does not drift with tick jitter.
        if self._next_check == -math.inf:
            self._next_check = now
        while self._next_check <= now + 1e-9:
            self._next_check += c.period_s
        if self._plugin is not None:
            send = bool(self._plugin.should_send(own, self._last_sent, now))
        else:
            send = c.kind == "periodic" or self._deviates(own, now)
        if send:
            self._last_sent = own
        return send

    def _deviates(self, own: VehicleState, now: float) -> bool:
        last = self._last_sent
        if last is None or now - last.t >= self.config.max_silence_s - 1e-9:
            return True
        predicted = last.extrapolate(own.t)
        return (
            own.distance_to(predicted) > self.config.threshold_m
            or abs(own.speed - last.speed) > self.config.speed_threshold_mps
        )
