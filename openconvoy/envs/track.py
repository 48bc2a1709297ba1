"""Track files in the original OpenConvoy JSON format, so existing lab tracks load unchanged.

The format (as the original implementation's beacon reads it)::

    {
      "name": "garage_loop",
      "center": {"lat": 28.6023, "lon": -81.1953},
      "straights": [{"start": {"lat": .., "lon": ..}, "end": {"lat": .., "lon": ..},
                     "speed": 1.0}, ...],
      "turns":     [{"start": {..}, "end": {..}, "speed": 1.0, "direction": "left"}, ...],
      "closed_loop": true                      # optional, our extension (default true)
    }

Semantics, following the original: the track is ``straights[0], turns[0], straights[1],
turns[1], ...``; turn ``i`` starts at its ``start`` point heading along straight ``i`` and
turns (``direction`` ``left`` = counter-clockwise, ``right`` = clockwise) until it heads
along straight ``i + 1`` (straight 0 again on a closed loop), on a circular arc whose
radius follows from the chord between its start and end and the turn angle
(``chord / (2 sin(angle / 2))``). Extra straights after the last turn are appended; turns
without a following straight are ignored, as in the original. ``speed`` (m/s) is the
leader's speed along that segment. ``center`` is the local ENU origin. Unknown keys are
an error naming the key.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path as FilePath
from typing import Any

import numpy as np

from openconvoy.comms.geodesy import Origin, geodetic_to_enu
from openconvoy.core.errors import InputFileError, MissingFileError
from openconvoy.envs.path import Path

_TOP_KEYS = {"name", "center", "straights", "turns", "closed_loop"}
_STRAIGHT_KEYS = {"start", "end", "speed"}
_TURN_KEYS = {"start", "end", "speed", "direction"}
_POINT_KEYS = {"lat", "lon"}
MAX_SPEED_MPS = 50.0
"""Fastest segment speed a track may ask for (m/s)."""
MAX_EXTENT_M = 50_000.0
"""Farthest a track point may lie from the track's centre (m): beyond, it is a typo."""


@dataclass(frozen=True)
class Track:
    """A loaded track: its path in ENU around ``origin`` and the speed along it.

    Attributes:
        name: the file's ``name``.
        origin: the file's ``center`` (altitude 0).
        path: the driven line, metres ENU.
        speed_s: arc lengths (m, increasing from 0) where each segment starts.
        speed_mps: the speed of each segment, m/s.
    """

    name: str
    origin: Origin
    path: Path
    speed_s: np.ndarray
    speed_mps: np.ndarray

    def speed_at(self, s: float) -> float:
        """The track's speed (m/s) at arc length ``s`` (m)."""
        if self.path.closed:
            s = s % self.path.length
        i = int(np.searchsorted(self.speed_s, s, side="right")) - 1
        return float(self.speed_mps[max(i, 0)])


def _check_keys(obj: Any, allowed: set[str], required: set[str], where: str) -> None:
    if not isinstance(obj, dict):
        raise InputFileError(f"{where}: expected an object, got {type(obj).__name__}")
    unknown = set(obj) - allowed
    if unknown:
        raise InputFileError(f"{where}: unknown key(s): {', '.join(sorted(unknown))}")
    missing = required - set(obj)
    if missing:
        raise InputFileError(f"{where}: missing key(s): {', '.join(sorted(missing))}")


def _number(
    obj: dict[str, Any], key: str, where: str, lo: float, hi: float, lo_open: bool = False
) -> float:
    """``obj[key]`` as a finite number in [lo, hi] (``(lo, hi]`` with ``lo_open``)."""
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputFileError(f"{where}.{key}: expected a number, got {v!r}")
    if not (math.isfinite(v) and (lo < v if lo_open else lo <= v) and v <= hi):
        raise InputFileError(
            f"{where}.{key}: {v!r} is out of range; allowed: a finite number in "
            f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        )
    return float(v)


def _latlon(obj: Any, where: str) -> tuple[float, float]:
    _check_keys(obj, _POINT_KEYS, _POINT_KEYS, where)
    return _number(obj, "lat", where, -90.0, 90.0), _number(obj, "lon", where, -180.0, 180.0)


def _point(obj: Any, origin: Origin, where: str) -> np.ndarray:
    lat, lon = _latlon(obj, where)
    x, y, _ = geodetic_to_enu(origin, lat, lon)
    if math.hypot(x, y) > MAX_EXTENT_M:
        raise InputFileError(
            f"{where}: {math.hypot(x, y) / 1000:.0f} km from the track's center "
            f"(at most {MAX_EXTENT_M / 1000:g} km)"
        )
    return np.array([x, y])


def _arc(
    start: np.ndarray, h0: float, h1: float, end: np.ndarray, left: bool, step_m: float
) -> list[tuple[float, float]]:
    """Points of the arc leaving ``start`` at heading ``h0`` and turning to ``h1``."""
    turn = (h1 - h0) % (2 * math.pi) if left else (h0 - h1) % (2 * math.pi)
    if turn < 1e-6:
        return [tuple(end)]
    chord = float(np.hypot(*(end - start)))
    radius = chord / (2.0 * math.sin(turn / 2.0)) if turn < 2 * math.pi - 1e-6 else chord
    sign = 1.0 if left else -1.0
    # Centre is a radius away on the turning side of the start heading.
    cx = start[0] - sign * radius * math.sin(h0)
    cy = start[1] + sign * radius * math.cos(h0)
    k = max(4, int(math.ceil(radius * turn / step_m)))
    pts = []
    for j in range(1, k + 1):
        h = h0 + sign * turn * j / k
        pts.append((cx + sign * radius * math.sin(h), cy - sign * radius * math.cos(h)))
    return pts


def parse_track(
    data: dict[str, Any],
    closed_loop: bool | None = None,
    step_m: float = 0.25,
    source: str = "track",
) -> Track:
    """Build a ``Track`` from the decoded JSON of a track file.

    ``closed_loop`` overrides the file's optional ``closed_loop`` (default true, as the
    original beacon's default). ``step_m`` is the arc sampling step, metres.
    """
    origin, closed, straights, turns = _header(data, closed_loop, source)
    segs = _straights(straights, origin, source)
    headings = [math.atan2(b[1] - a[1], b[0] - a[0]) for a, b, _ in segs]
    if closed and len(segs) > 1:
        pairs = [(headings[i], headings[(i + 1) % len(segs)]) for i in range(len(segs))]
    else:
        pairs = [(headings[i], headings[i + 1]) for i in range(len(segs) - 1)]
    n_turns = min(len(turns), len(pairs))
    line = _Polyline()
    for i, (a, b, v) in enumerate(segs):
        line.section(v, start_at_zero=not line.points)
        line.add(tuple(a))
        line.add(tuple(b))
        if i < n_turns:
            ta, tb, left, speed = _turn(turns[i], origin, f"{source}: turns[{i}]")
            line.section(speed)
            line.add(tuple(ta))
            h0, h1 = pairs[i]
            for p in _arc(ta, h0, h1, tb, left, step_m):
                line.add(p)
    return Track(
        name=str(data["name"]),
        origin=origin,
        path=Path(np.array(line.points), closed=closed),
        speed_s=np.array(line.starts),
        speed_mps=np.array(line.speeds),
    )


def _header(
    data: dict[str, Any], closed_loop: bool | None, source: str
) -> tuple[Origin, bool, list[Any], list[Any]]:
    """The file's top level checked: origin, whether the track closes, straights, turns."""
    _check_keys(data, _TOP_KEYS, {"name", "center", "straights", "turns"}, source)
    origin = Origin(*_latlon(data["center"], f"{source}: center"))
    if not isinstance(data["name"], str):
        raise InputFileError(f"{source}: name: expected a string, got {data['name']!r}")
    flag = data.get("closed_loop", True)
    if not isinstance(flag, bool):
        raise InputFileError(f"{source}: closed_loop: expected true or false, got {flag!r}")
    closed = flag if closed_loop is None else closed_loop
    straights = data["straights"]
    turns = data["turns"]
    for key, value in (("straights", straights), ("turns", turns)):
        if not isinstance(value, list):
            raise InputFileError(f"{source}: {key}: expected a list, got {value!r}")
    if not straights:
        raise InputFileError(f"{source}: a track needs at least one straight")
    return origin, closed, straights, turns


def _straights(
    straights: list[Any], origin: Origin, source: str
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Each straight checked: ENU start and end (m) and its speed (m/s)."""
    segs = []
    for i, st in enumerate(straights):
        where = f"{source}: straights[{i}]"
        _check_keys(st, _STRAIGHT_KEYS, _STRAIGHT_KEYS, where)
        a = _point(st["start"], origin, f"{where}.start")
        b = _point(st["end"], origin, f"{where}.end")
        if np.hypot(*(b - a)) < 1e-6:
            raise InputFileError(f"{where}: start and end coincide")
        segs.append((a, b, _number(st, "speed", where, 0.0, MAX_SPEED_MPS, lo_open=True)))
    return segs


def _turn(tn: Any, origin: Origin, where: str) -> tuple[np.ndarray, np.ndarray, bool, float]:
    """A turn checked: ENU start and end (m), whether it turns left, its speed (m/s)."""
    _check_keys(tn, _TURN_KEYS, _TURN_KEYS, where)
    direction = tn["direction"]
    if direction not in ("left", "right"):
        raise InputFileError(f"{where}: direction must be 'left' or 'right', got {direction!r}")
    ta = _point(tn["start"], origin, f"{where}.start")
    tb = _point(tn["end"], origin, f"{where}.end")
    speed = _number(tn, "speed", where, 0.0, MAX_SPEED_MPS, lo_open=True)
    return ta, tb, direction == "left", speed


class _Polyline:
    """The track's points (ENU m, no repeats) and its speed sections (start arc m, m/s)."""

    def __init__(self) -> None:
        self.points: list[tuple[float, float]] = []
        self.starts: list[float] = []
        self.speeds: list[float] = []

    def arc_length(self) -> float:
        if len(self.points) < 2:
            return 0.0
        p = np.asarray(self.points)
        return float(np.hypot(*np.diff(p, axis=0).T).sum())

    def section(self, speed: float, start_at_zero: bool = False) -> None:
        """A speed section starting here (at 0 for the first)."""
        self.starts.append(0.0 if start_at_zero else self.arc_length())
        self.speeds.append(speed)

    def add(self, pt: tuple[float, float]) -> None:
        points = self.points
        if not points or math.hypot(pt[0] - points[-1][0], pt[1] - points[-1][1]) > 1e-6:
            points.append((float(pt[0]), float(pt[1])))


def load_track(path: str | FilePath, closed_loop: bool | None = None) -> Track:
    """Load a track file (original OpenConvoy JSON format, see the module docstring)."""
    p = FilePath(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MissingFileError(f"no such track file: {p}") from None
    except IsADirectoryError:
        raise InputFileError(f"{p}: is a directory, not a track file") from None
    except UnicodeDecodeError:
        raise InputFileError(f"{p}: not a text file (a track is JSON)") from None
    except json.JSONDecodeError as e:
        raise InputFileError(f"{p}: not valid JSON ({e})") from None
    return parse_track(data, closed_loop=closed_loop, source=str(p))


def example_track_path() -> FilePath:
    """The example track shipped with the package (a small lab oval)."""
    return FilePath(__file__).with_name("tracks") / "example_oval.json"
