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

from openconvoy.bridge import mavproto as mp
from openconvoy.bridge.link import Autopilot, LinkTimeout

_FAILSAFE_TEXT_S = 3.0  # a "failsafe" STATUSTEXT this recent explains a mode change


class VehicleWatch:
    """The autopilot's identity and state as its messages report it.

    Attributes:
        target: (system id, component id) of the autopilot (None before its heartbeat).
        autopilot_id: its MAV_AUTOPILOT (3 ArduPilot, 12 PX4; None before a heartbeat).
        mode: mode name of the latest heartbeat (``"UNKNOWN"`` before one).
        armed: armed bit of the latest heartbeat.
        t_heartbeat: clock (s) of the latest heartbeat.
        heartbeats: heartbeats counted (to wait for one after now).
        acks: command id -> (result, clock s) of its latest final COMMAND_ACK.
        texts: recent (clock s, severity, text) STATUSTEXTs, oldest first.
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
        self.acks: dict[int, tuple[int, float]] = {}
        self.texts: deque[tuple[float, int, str]] = deque(maxlen=32)

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
        """Keep a STATUSTEXT."""
        text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
        self.texts.append((self._clock(), msg.severity, text.rstrip("\x00")))

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

    def who_set_mode(self) -> str:
        """Who changed the mode, as far as MAVLink tells: a recent failsafe STATUSTEXT
        names the autopilot itself; otherwise it was not this link."""
        now = self._clock()
        for t, _, text in reversed(self.texts):
            if now - t > _FAILSAFE_TEXT_S:
                break
            if "failsafe" in text.lower():
                return f"the autopilot's failsafe ({text.strip()!r})"
        if self.autopilot_id == mp.AUTOPILOT_PX4:
            return "not this link (the RC, another GCS, or a PX4 failsafe without a text)"
        return "not this link (the RC mode switch, MODE_CH, or another GCS)"
