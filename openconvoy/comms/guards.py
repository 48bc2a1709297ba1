"""What a V2V receiver keeps about each sender beyond the message itself (pure, no I/O).

- ``SkewMeter``: how far a sender's clock is off ours, from the time its messages claim
  and when we received them (the largest ``t_claimed - t_rx`` over the last few seconds:
  the network only ever adds delay, so the largest is the least delayed).
- ``FrameMemory``: unsigned frames already delivered, for an hour (bounded): a verbatim
  replay is a duplicate even when its secMark, which repeats every minute, looks fresh.
- ``JumpCheck``: a sender whose positions jump further than any vehicle drives between
  two messages (two stations sending under one identity, D53).
- ``Alerts``: one-line operator messages, at most one per kind and sender per period.

Times are seconds (Unix, the shared clock); positions metres (ENU).
"""

from __future__ import annotations

import hashlib
import math
from collections import deque
from dataclasses import dataclass

#: Samples older than this (s) no longer count for a sender's clock offset.
SKEW_HORIZON_S = 5.0
#: Samples kept per sender.
SKEW_SAMPLES = 64
#: How long (s) a delivered unsigned frame is remembered (replays up to an hour late).
FRAME_MEMORY_S = 3600.0
#: Frames remembered at most: an hour of two senders at 20 Hz (23 MB at the bound, measured).
FRAME_MEMORY_MAX = 144_000
#: Fastest plausible vehicle (m/s) and the position noise allowed on top (m).
JUMP_SPEED_MPS = 70.0
JUMP_SLACK_M = 10.0
#: An alert of one kind about one sender is repeated at most this often (s).
ALERT_PERIOD_S = 5.0


def sec_mark_offset(sec_mark_ms: int, t_rx: float) -> float:
    """A J2735 sender's clock minus ours (s), wrapped to [-30, 30) s, from its secMark and
    our receive time ``t_rx`` (the network delay is included, as a negative bias)."""
    ours = (t_rx * 1000.0) % 60000.0
    d = (sec_mark_ms - ours + 30000.0) % 60000.0 - 30000.0
    return d / 1000.0


class SkewMeter:
    """Clock offset per sender: the largest ``t_claimed - t_rx`` of its recent messages."""

    def __init__(self) -> None:
        self._samples: dict[int, deque[tuple[float, float]]] = {}

    def sample(self, sender: int, offset_s: float, t_rx: float) -> None:
        """Record one message of ``sender`` whose claimed time minus ``t_rx`` is ``offset_s``."""
        if not math.isfinite(offset_s):
            return
        q = self._samples.setdefault(sender, deque(maxlen=SKEW_SAMPLES))
        q.append((t_rx, offset_s))

    def offset(self, sender: int, now: float) -> float | None:
        """``sender``'s clock minus ours (s; positive: ahead), None when not heard lately."""
        q = self._samples.get(sender)
        if not q:
            return None
        recent = [o for t, o in q if now - t <= SKEW_HORIZON_S]
        return max(recent) if recent else None

    def worst(self, now: float) -> tuple[int, float] | None:
        """(sender, offset) of the sender whose clock is furthest off, None if none heard."""
        best: tuple[int, float] | None = None
        for sender in self._samples:
            o = self.offset(sender, now)
            if o is not None and (best is None or abs(o) > abs(best[1])):
                best = (sender, o)
        return best


class FrameMemory:
    """Digests of frames already delivered, forgotten after ``FRAME_MEMORY_S`` or when
    more than ``FRAME_MEMORY_MAX`` are held (oldest first)."""

    def __init__(self, horizon_s: float = FRAME_MEMORY_S, max_frames: int = FRAME_MEMORY_MAX):
        self.horizon_s = horizon_s
        self.max_frames = max_frames
        self._seen: set[bytes] = set()
        self._order: deque[tuple[float, bytes]] = deque()

    def seen(self, frame: bytes, now: float) -> bool:
        """Whether ``frame`` (its exact octets) was remembered; remembers it if not."""
        while self._order and (
            now - self._order[0][0] > self.horizon_s or len(self._order) > self.max_frames
        ):
            self._seen.discard(self._order.popleft()[1])
        key = hashlib.blake2b(frame, digest_size=12).digest()
        if key in self._seen:
            return True
        self._seen.add(key)
        self._order.append((now, key))
        return False

    def __len__(self) -> int:
        return len(self._seen)


@dataclass
class Jump:
    """A position jump: ``distance_m`` in ``dt_s`` seconds."""

    distance_m: float
    dt_s: float


class JumpCheck:
    """Flags a sender whose consecutive positions are further apart than a vehicle can
    drive in between (``JUMP_SPEED_MPS`` times the time between, plus ``JUMP_SLACK_M``)."""

    def __init__(self) -> None:
        self._last: dict[int, tuple[float, float, float]] = {}
        self.jumps: dict[int, int] = {}

    def check(self, sender: int, t: float, x: float, y: float) -> Jump | None:
        """Record ``sender`` at (x, y) at its time ``t``; the jump from its last position if
        implausible, else None."""
        last = self._last.get(sender)
        self._last[sender] = (t, x, y)
        if last is None:
            return None
        dt = abs(t - last[0])
        d = math.hypot(x - last[1], y - last[2])
        if d > JUMP_SLACK_M + JUMP_SPEED_MPS * dt:
            self.jumps[sender] = self.jumps.get(sender, 0) + 1
            return Jump(d, dt)
        return None


class Alerts:
    """Operator lines, at most one per (kind, sender) per ``ALERT_PERIOD_S``."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, int], float] = {}
        self.pending: list[str] = []

    def raise_(
        self, kind: str, sender: int, now: float, line: str, period_s: float = ALERT_PERIOD_S
    ) -> bool:
        """Queue ``line`` unless this kind about this sender was said in the last
        ``period_s`` seconds."""
        key = (kind, sender)
        last = self._last.get(key)
        if last is not None and now - last < period_s:
            return False
        self._last[key] = now
        self.pending.append(line)
        return True

    def take(self) -> list[str]:
        """The lines queued since the last call."""
        out, self.pending = self.pending, []
        return out
