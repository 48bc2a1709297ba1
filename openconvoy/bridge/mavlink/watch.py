"""What ``MavlinkLink`` knows of its autopilot from heartbeats, COMMAND_ACKs and STATUSTEXTs.

Per connection (``reset`` when reopening): which system and component is the vehicle, its
firmware, mode and armed bit, when its heartbeat last came, the answers to our commands
and its recent status texts (the reasons for refusals, and failsafe announcements).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

from openconvoy.bridge.link import Autopilot, LinkTimeout
from openconvoy.bridge.mavlink import protocol as mp

_FAILSAFE_TEXT_S = 3.0  # a "failsafe" STATUSTEXT this recent explains a mode change
_TEXT_CHUNK = 50  # STATUSTEXT's text field, bytes: a shorter chunk is a text's last
_CHUNK_WAIT_S = 1.0  # a chunked text still unfinished this long is kept as it stands
_FAILSAFE_STATES = {5: "CRITICAL", 6: "EMERGENCY"}  # MAV_STATE: "non-normal mode"


class VehicleWatch:
    """The autopilot's identity and state as its messages report it.

    Attributes:
        target: (system id, component id) of the autopilot (None before its heartbeat).
        autopilot_id: its MAV_AUTOPILOT (3 ArduPilot, 12 PX4; None before a heartbeat).
        mode: mode name of the latest heartbeat (``"UNKNOWN"`` before one).
        armed: armed bit of the latest heartbeat.
        t_heartbeat: clock (s) of the latest heartbeat.
        heartbeats: heartbeats counted (to wait for one after now).
        system_status: MAV_STATE of the latest heartbeat (5 CRITICAL while a failsafe is
            active: PX4's offboard-loss failsafe, shared/sitl-px4 row 16; ArduPilot Rover
            reports CRITICAL while ``failsafe.triggered``).
        acks: command id -> (result, clock s) of its latest final COMMAND_ACK.
        texts: recent (clock s, severity, text) STATUSTEXTs, oldest first; a text the
            autopilot sent in chunks (longer than 50 bytes: PX4's "Arming denied: ..."
            comes as two) is kept once, whole.
    """

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.reset()

    def reset(self) -> None:
        """Forget the vehicle (a new connection)."""
        self.target: tuple[int, int] | None = None
        self.autopilot_id: int | None = None
        self.mode = "UNKNOWN"
        self.armed = False
        self.t_heartbeat = -math.inf
        self.heartbeats = 0
        self.system_status = 0
        self.acks: dict[int, tuple[int, float]] = {}
        self.texts: deque[tuple[float, int, str]] = deque(maxlen=32)
        self._chunks: dict[int, tuple[float, int, str]] = {}  # id -> (clock s, severity, so far)

    @property
    def system_id(self) -> int | None:
        """The vehicle's MAVLink system id (None before its heartbeat)."""
        return None if self.target is None else self.target[0]

    @property
    def status_texts(self) -> list[str]:
        """Recent STATUSTEXT lines from the autopilot, oldest first."""
        return [text for _, _, text in self.texts]

    def autopilot(self) -> Autopilot:
        """``"ardupilot"`` or ``"px4"``; raises ``LinkTimeout`` before identification."""
        if self.autopilot_id == mp.AUTOPILOT_PX4:
            return "px4"
        if self.autopilot_id is None:
            raise LinkTimeout("vehicle not identified yet: call connect() first")
        return "ardupilot"

    def is_autopilot_heartbeat(self, msg: Any) -> bool:
        """Whether a HEARTBEAT is our autopilot's (the first autopilot seen becomes the
        target). Not GCSs, companions, gimbals, ADS-B receivers or cameras (those report
        autopilot INVALID), nor other vehicles."""
        m = mp.mav()
        if msg.type in (
            mp.MAV_TYPE_GCS,
            m.MAV_TYPE_ONBOARD_CONTROLLER,
            m.MAV_TYPE_GIMBAL,
            m.MAV_TYPE_ADSB,
        ):
            return False
        if msg.autopilot == m.MAV_AUTOPILOT_INVALID:
            return False
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.target is None:
            self.target = src
        return src == self.target

    def on_text(self, msg: Any) -> None:
        """Keep a STATUSTEXT, joining the chunks of a long one (MAVLink's ``id`` and
        ``chunk_seq``: the chunk shorter than 50 bytes ends the text)."""
        raw = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
        text, now = raw.rstrip("\x00"), self._clock()
        chunk_id = int(getattr(msg, "id", 0) or 0)
        if chunk_id == 0 or int(getattr(msg, "chunk_seq", 0) or 0) == 0:
            # Texts come one after another: an unfinished one lost its end.
            self._flush_chunks(math.inf)
        else:
            self._flush_chunks(now - _CHUNK_WAIT_S)
        if chunk_id == 0:
            self.texts.append((now, msg.severity, text.rstrip()))  # PX4 ends texts with a tab
            return
        t0, severity, so_far = self._chunks.pop(chunk_id, (now, msg.severity, ""))
        if len(text.encode()) < _TEXT_CHUNK:
            self.texts.append((t0, severity, (so_far + text).rstrip()))
        else:
            self._chunks[chunk_id] = (t0, severity, so_far + text)

    def _flush_chunks(self, before: float) -> None:
        """Keep, as they stand, unfinished chunked texts begun before ``before`` (clock s)."""
        for chunk_id, (t0, severity, so_far) in list(self._chunks.items()):
            if t0 < before:
                del self._chunks[chunk_id]
                self.texts.append((t0, severity, so_far.rstrip()))

    def on_ack(self, msg: Any) -> bool:
        """Keep a final COMMAND_ACK; True when it is a refusal (IN_PROGRESS is skipped)."""
        if msg.result == mp.mav().MAV_RESULT_IN_PROGRESS:
            return False
        self.acks[msg.command] = (msg.result, self._clock())
        return bool(msg.result != mp.RESULT_ACCEPTED)

    def reason(self, since: float = -math.inf) -> str:
        """The autopilot's newest status text received after ``since`` (clock s)."""
        if self.texts and self.texts[-1][0] >= since:
            return self.texts[-1][2]
        return ""

    def refusal(self, since: float) -> str:
        """Why the autopilot refused a command sent after ``since`` (clock s): its
        warnings and errors since then, oldest first, each once and joined by "; "
        (ArduPilot sends one text per failed arming check: "Arm: Gyros inconsistent",
        then "Arm: AHRS: not using configured AHRS type"); else its newest text since."""
        warning = mp.mav().MAV_SEVERITY_WARNING
        found = [text for t, sev, text in self.texts if t >= since and sev <= warning]
        return "; ".join(dict.fromkeys(found)) or self.reason(since)

    def who_set_mode(self) -> str:
        """Who changed the mode, as far as MAVLink tells: a recent failsafe STATUSTEXT, or
        a heartbeat with system status CRITICAL/EMERGENCY (the failsafe flag itself, which
        a lost or late text cannot hide), names the autopilot; otherwise it was someone
        other than this link."""
        now = self._clock()
        for t, _, text in reversed(self.texts):
            if now - t > _FAILSAFE_TEXT_S:
                break
            if "failsafe" in text.lower():
                return f"the autopilot's failsafe ({text.strip()!r})"
        if self.system_status in _FAILSAFE_STATES:
            state = _FAILSAFE_STATES[self.system_status]
            return f"the autopilot's failsafe (heartbeat system status {state}; no failsafe text)"
        if self.autopilot_id == mp.AUTOPILOT_PX4:
            return "someone other than this link (the RC, another GCS, or a PX4 failsafe without a text)"
        return "someone other than this link (the RC mode switch, MODE_CH, or another GCS)"
