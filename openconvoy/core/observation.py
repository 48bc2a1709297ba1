"""The observation layout: a fixed-size float array built from R^i, and its named view.

Layout (version 1), in order (DESIGN.md, Observation):

1. state slots ``leader``, ``pred_1`` .. ``pred_M`` (1 = immediate predecessor),
   ``follower`` (the immediate follower): each the last ``k`` states received, newest
   first, as ``STATE_FEATURES`` relative to the ego (ego frame: x forward, y left);
2. own state, ``OWN_FEATURES``;
3. derived features for each target slot ``leader``, ``pred_1`` .. ``pred_M``
   (``DERIVED_FEATURES``): arc-length gap along that vehicle's trail, the desired gap to it
   from the spacing policy, their difference, its (latest) speed and a validity flag. The
   ``leader`` target is valid only when the leader is not already a ``pred_m`` slot;
4. path features (``PATH_FEATURES``) of the nearest heard predecessor's trail: cross-track
   offset, heading error, and lookahead points 0.5 s, 1 s, 2 s ahead along it.

Learned policies record ``(version, M, k)``; a mismatch at load time is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from openconvoy.core.errors import ConfigError
from openconvoy.core.state import wrap_angle

LAYOUT_VERSION = 1

STATE_FEATURES = ("dx", "dy", "dheading", "speed", "accel", "age", "valid")
OWN_FEATURES = ("speed", "accel", "yaw_rate")
DERIVED_FEATURES = ("arc_gap", "desired_gap", "spacing_error", "speed", "valid")
LOOKAHEAD_S = (0.5, 1.0, 2.0)
"""Lookahead times of the path points (s); each at least that many metres ahead."""
PATH_FEATURES = (
    "cross_track",
    "heading_error",
    "la0_x",
    "la0_y",
    "la1_x",
    "la1_y",
    "la2_x",
    "la2_y",
    "valid",
)
MAX_AGE_S = 10.0
"""Ages are clipped here so the array stays finite."""


def to_ego(c: float, s: float, dx: float, dy: float) -> tuple[float, float]:
    """A world offset ``dx``, ``dy`` (m) in the ego frame (m: ahead, to the left), for
    the ego heading's cosine ``c`` and sine ``s``."""
    return c * dx + s * dy, -s * dx + c * dy


def ego_state(
    c: float, s: float, dx: float, dy: float, dheading: float, age: float
) -> tuple[float, float, float, float]:
    """A sender's state slot's geometry: its offset (m) in the ego frame (as ``to_ego``,
    written out: the simulator's Python path calls this per state), its heading less the
    ego's wrapped to [-π, π) (rad), its message age held within [0, ``MAX_AGE_S``] (s)."""
    return (
        c * dx + s * dy,
        -s * dx + c * dy,
        wrap_angle(dheading),
        MAX_AGE_S if age > MAX_AGE_S else (age if age > 0.0 else 0.0),
    )


@dataclass(frozen=True)
class ObservationLayout:
    """Slot sizes and offsets for ``M`` predecessors and ``k`` states per vehicle."""

    M: int = 2
    k: int = 3
    version: int = LAYOUT_VERSION
    slots: tuple[str, ...] = field(init=False)
    targets: tuple[str, ...] = field(init=False)
    slot_size: int = field(init=False)
    own_offset: int = field(init=False)
    derived_offset: int = field(init=False)
    path_offset: int = field(init=False)
    size: int = field(init=False)

    def __post_init__(self) -> None:
        if self.M < 1 or self.k < 1:
            raise ConfigError(
                f"observation layout needs M >= 1 and k >= 1, got M={self.M}, k={self.k}"
            )
        preds = tuple(f"pred_{m}" for m in range(1, self.M + 1))
        # Offsets are computed once: the member reads them on every tick.
        slots = ("leader", *preds, "follower")
        targets = ("leader", *preds)
        slot_size = self.k * len(STATE_FEATURES)
        own = len(slots) * slot_size
        derived = own + len(OWN_FEATURES)
        path = derived + len(targets) * len(DERIVED_FEATURES)
        for name, value in (
            ("slots", slots),
            ("targets", targets),
            ("slot_size", slot_size),
            ("own_offset", own),
            ("derived_offset", derived),
            ("path_offset", path),
            ("size", path + len(PATH_FEATURES)),
        ):
            object.__setattr__(self, name, value)

    def slot_offset(self, slot: str) -> int:
        return self.slots.index(slot) * self.slot_size

    def target_offset(self, target: str) -> int:
        return self.derived_offset + self.targets.index(target) * len(DERIVED_FEATURES)

    def describe(self) -> dict[str, int]:
        """What a trained policy records: ``{"version", "M", "k", "size"}``."""
        return {"version": self.version, "M": self.M, "k": self.k, "size": self.size}

    def check_compatible(self, recorded: dict[str, int]) -> None:
        """Raise ValueError naming the difference when ``recorded`` is another layout."""
        mine = self.describe()
        diffs = [
            f"{key} {recorded.get(key)} vs {mine[key]}"
            for key in mine
            if recorded.get(key) != mine[key]
        ]
        if diffs:
            raise ValueError(
                "policy was trained for another observation layout ("
                + ", ".join(diffs)
                + " in this convoy config)"
            )

    def zeros(self) -> np.ndarray:
        return np.zeros(self.size, dtype=np.float32)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` float32 arrays: finite where the layout bounds a feature (validity
        flags in [0, 1], ages in [0, ``MAX_AGE_S``], heading differences in [-π, π]),
        infinite elsewhere (positions, speeds, gaps)."""
        low = np.full(self.size, -np.inf, dtype=np.float32)
        high = np.full(self.size, np.inf, dtype=np.float32)
        pi = float(np.float32(np.pi))

        def bound(offset: int, lo: float, hi: float) -> None:
            low[offset], high[offset] = lo, hi

        nf = len(STATE_FEATURES)
        for slot in self.slots:
            for j in range(self.k):
                o = self.slot_offset(slot) + j * nf
                bound(o + STATE_FEATURES.index("dheading"), -pi, pi)
                bound(o + STATE_FEATURES.index("age"), 0.0, MAX_AGE_S)
                bound(o + STATE_FEATURES.index("valid"), 0.0, 1.0)
        for target in self.targets:
            bound(self.target_offset(target) + DERIVED_FEATURES.index("valid"), 0.0, 1.0)
        bound(self.path_offset + PATH_FEATURES.index("heading_error"), -pi, pi)
        bound(self.path_offset + PATH_FEATURES.index("valid"), 0.0, 1.0)
        return low, high

    def view(self, obs: np.ndarray) -> ObservationView:
        return ObservationView(self, obs)


class ObservationView:
    """Named read access to an observation array (what classical policies use)."""

    def __init__(self, layout: ObservationLayout, obs: np.ndarray) -> None:
        if obs.shape != (layout.size,):
            raise ValueError(f"observation has shape {obs.shape}, layout expects ({layout.size},)")
        self.layout = layout
        self.obs = obs

    def states(self, slot: str) -> np.ndarray:
        """The slot's ``k`` states, newest first, shape (k, len(STATE_FEATURES))."""
        o = self.layout.slot_offset(slot)
        return self.obs[o : o + self.layout.slot_size].reshape(self.layout.k, len(STATE_FEATURES))

    def target(self, target: str) -> dict[str, float]:
        o = self.layout.target_offset(target)
        return {f: float(self.obs[o + i]) for i, f in enumerate(DERIVED_FEATURES)}

    def valid_targets(self) -> list[dict[str, float]]:
        """Derived features of every valid target, nearest predecessor first."""
        order = self.layout.targets[1:] + ("leader",)
        out = [self.target(t) for t in order]
        return [d for d in out if d["valid"] > 0.5]

    @property
    def own(self) -> dict[str, float]:
        o = self.layout.own_offset
        return {f: float(self.obs[o + i]) for i, f in enumerate(OWN_FEATURES)}

    @property
    def own_speed(self) -> float:
        return float(self.obs[self.layout.own_offset])

    @property
    def path(self) -> dict[str, float]:
        o = self.layout.path_offset
        return {f: float(self.obs[o + i]) for i, f in enumerate(PATH_FEATURES)}
