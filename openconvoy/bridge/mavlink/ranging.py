"""Forward rangefinder intake for ``MavlinkLink``: DISTANCE_SENSOR -> range and range rate.

Only orientation 0 (MAV_SENSOR_ROTATION_NONE, forward) counts; PX4 SIH streams a downward
one (orientation 25), which is ignored. The rate is the least-squares slope over the last
``RANGE_WINDOW_S`` of readings: 1 cm steps at 10-20 Hz make a plain difference ±0.2 m/s
of noise.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

RANGE_WINDOW_S = 0.5  # range rate: least-squares slope over this much of the newest ranges
RANGE_GAP_S = 0.5  # a range older than this (vehicle time) starts a new slope


class RangeIntake:
    """The newest forward range.

    Attributes:
        range_m: the range (m), NaN when nothing is in range or no sensor reported.
        range_rate: its rate of change (m/s, negative = closing), NaN when unknown.
        t_range: link clock (s) of the newest forward reading (-inf if never).
    """

    def __init__(self) -> None:
        self._ranges: deque[tuple[float, float]] = deque(maxlen=64)  # (vehicle time s, m)
        self.range_m = math.nan
        self.range_rate = math.nan
        self.t_range = -math.inf

    def on_distance(self, msg: Any, now: float) -> None:
        """A DISTANCE_SENSOR received at link-clock ``now`` (s): range (cm -> m) and its
        rate. A reading outside [min_distance, max_distance) means nothing in range."""
        if msg.orientation != 0:
            return
        self.t_range = now
        cm = msg.current_distance
        ranges = self._ranges
        if cm == 0xFFFF or cm < msg.min_distance or cm >= msg.max_distance or cm <= 0:
            ranges.clear()
            self.range_m = self.range_rate = math.nan
            return
        t = msg.time_boot_ms * 1e-3
        if ranges and not 0.0 < t - ranges[-1][0] <= RANGE_GAP_S:
            ranges.clear()  # a gap, a repeat or a reboot: start a new slope
        ranges.append((t, cm * 0.01))
        while t - ranges[0][0] > RANGE_WINDOW_S:
            ranges.popleft()
        self.range_m = cm * 0.01
        n = len(ranges)
        if n < 2:
            self.range_rate = math.nan
            return
        mt = sum(p[0] for p in ranges) / n
        mr = sum(p[1] for p in ranges) / n
        stt = sum((p[0] - mt) ** 2 for p in ranges)
        self.range_rate = sum((p[0] - mt) * (p[1] - mr) for p in ranges) / stt
