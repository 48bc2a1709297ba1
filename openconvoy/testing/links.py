"""Fakes of ``bridge.link.VehicleLink`` for tests of the deploy runner (no autopilot, no
sockets), and a wrapper recording what a real link sent.

- ``FakeLink``: a vehicle wherever the test puts it, driving each setpoint at once (an
  ideal autopilot), kinematically integrated on an injected clock.
- ``ScriptedLink``: ``FakeLink`` plus what ``MavlinkLink`` reports: a takeover at a time,
  telemetry that freezes at a time, a rangefinder reading, finite braking, setpoints
  refused from a time on, and a record of holds and disarms.
- ``ReplayLink``: telemetry exactly as the test sets it (``state``, ``ranging``), always
  fresh; records the setpoints.
- ``RecordingLink``: delegates to a real link; records the setpoints that went out.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

from openconvoy.bridge.link import Telemetry
from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.core.state import VehicleState
from openconvoy.testing.clock import FakeClock


class _QuietLink:
    """What every fake shares: an ArduPilot that is connected, never lost, never taken
    over, and whose connect, reconnect and close do nothing. A fake is its own
    ``setpoints`` (``send``, ``stop``) and ``modes`` (``prepare_and_arm``, ``hold``,
    ``disarm``, the takeover)."""

    autopilot = "ardupilot"
    telemetry_timeout_s = 0.5
    heartbeat_timeout_s = 3.0
    takeover_reason = ""
    failsafe_took_over = False
    pilot_took_over = False
    lost = False

    def __init__(self) -> None:
        self.telemetry_rates: dict[str, float] = {}
        self.setpoints = self
        self.modes = self

    def connect(self, timeout_s: float) -> None:
        """Connected already."""

    def reconnect(self, timeout_s: float) -> None:
        """Never lost."""

    def close(self) -> None:
        """Nothing to release."""


class FakeLink(_QuietLink):
    """A vehicle that is wherever the test says, kinematically integrating setpoints.

    Starts at ``(x, y)`` (m, the convoy's ENU frame) heading ``heading`` (rad); each
    setpoint becomes its speed and heading at once (an ideal autopilot), and ``poll``
    moves it on by the ``clock`` time since the last poll (unless ``move`` is False).
    ``sent`` records ``(clock s, speed, heading)`` of each setpoint, ``holds`` counts HOLDs.
    """

    def __init__(
        self,
        clock: FakeClock,
        origin: Origin,
        vehicle_id: int,
        x: float,
        y: float,
        heading: float = 0.0,
        move: bool = True,
    ) -> None:
        super().__init__()
        self.clock, self.origin, self.vehicle_id = clock, origin, vehicle_id
        self.x, self.y, self.heading, self.speed = x, y, heading, 0.0
        self.move = move
        self.sent: list[tuple[float, float, float]] = []
        self.armed = False
        self.holds = 0
        self.pilot_took_over = False
        self._t = clock()

    def poll(self) -> Telemetry:
        """Fresh telemetry of where the vehicle is now."""
        now = self.clock()
        if self.move:
            dt = now - self._t
            self.x += self.speed * math.cos(self.heading) * dt
            self.y += self.speed * math.sin(self.heading) * dt
        self._t = now
        lat, lon, _ = enu_to_geodetic(self.origin, self.x, self.y)
        st = VehicleState(
            self.vehicle_id, self.clock.wall(), self.x, self.y, self.speed, self.heading
        )
        return Telemetry(st, lat, lon, "GUIDED", self.armed, now, now)

    def prepare_and_arm(self, timeout_s: float, on_status: Any = None) -> None:
        """Armed at once."""
        self.armed = True

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Recorded and driven at once (an ideal autopilot)."""
        self.sent.append((self.clock(), speed_mps, heading_rad))
        self.speed, self.heading = speed_mps, heading_rad
        return True

    def stop(self) -> bool:
        """A zero-speed setpoint on the current heading."""
        return self.send(0.0, self.heading)

    def hold(self, timeout_s: float = 2.0) -> None:
        """Counted in ``holds``."""
        self.holds += 1

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Disarmed at once."""
        self.armed = False


class ScriptedLink(FakeLink):
    """FakeLink plus what MavlinkLink reports: a takeover at a time, telemetry that freezes
    at a time, a rangefinder reading, finite braking, and a record of holds and disarms.

    Keywords (times on the link's clock, s): ``takeover_at`` (then a ``failsafe`` one or
    the pilot's), ``freeze_at`` (telemetry stops changing), ``refuse_at`` (setpoints are
    refused: PX4's stream ended), ``range_m``/``range_rate`` (the rangefinder, bumper to
    bumper), ``decel`` (m/s², the speed approaches the command at this rate; inf: at once),
    ``speed`` (m/s at the start). ``hold_log`` holds ``(clock, speed)`` of each HOLD.
    """

    def __init__(
        self,
        *args: Any,
        takeover_at: float = math.inf,
        failsafe: bool = False,
        freeze_at: float = math.inf,
        range_m: float = math.nan,
        range_rate: float = math.nan,
        decel: float = math.inf,
        speed: float = 0.0,
        refuse_at: float = math.inf,
        **kw: Any,
    ) -> None:
        super().__init__(*args, **kw)
        self.refuse_at = refuse_at
        self.takeover_at, self.failsafe, self.freeze_at = takeover_at, failsafe, freeze_at
        self.range_m, self.range_rate, self.decel = range_m, range_rate, decel
        self.speed = self.target = speed
        self.hold_log: list[tuple[float, float]] = []
        self.disarms = 0
        self._frozen: Telemetry | None = None

    @property  # a plain attribute in FakeLink, scripted here
    def pilot_took_over(self) -> bool:
        return self.clock() >= self.takeover_at

    @pilot_took_over.setter
    def pilot_took_over(self, value: bool) -> None:  # FakeLink.__init__ assigns it
        pass

    @property
    def failsafe_took_over(self) -> bool:  # type: ignore[override]  # scripted, read-only
        return self.pilot_took_over and self.failsafe

    @property
    def takeover_reason(self) -> str:  # type: ignore[override]  # scripted, read-only
        return (
            "mode changed from GUIDED to MANUAL, set by not this link (the RC mode switch)"
            if self.pilot_took_over
            else ""
        )

    def poll(self) -> Telemetry:
        """FakeLink's telemetry with the rangefinder's reading; frozen from ``freeze_at``."""
        now = self.clock()
        dt = now - self._t
        if math.isfinite(self.decel):  # the speed approaches the command at ``decel``
            step = self.decel * dt
            self.speed += max(-step, min(step, self.target - self.speed))
        tel = super().poll()
        if now >= self.freeze_at:
            if self._frozen is None:
                self._frozen = tel
            return self._frozen
        return replace(tel, range_m=self.range_m, range_rate_mps=self.range_rate, t_range=now)

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Refused after a takeover or from ``refuse_at``; else recorded, the speed then
        approaching it at ``decel``."""
        if self.pilot_took_over or self.clock() >= self.refuse_at:
            return False
        self.sent.append((self.clock(), speed_mps, heading_rad))
        self.heading = heading_rad
        if math.isfinite(self.decel):
            self.target = speed_mps
        else:
            self.speed = speed_mps
        return True

    def hold(self, timeout_s: float = 2.0) -> None:
        """Counted, with the clock and the speed at the request in ``hold_log``."""
        self.holds += 1
        self.hold_log.append((self.clock(), self.speed))

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Counted in ``disarms``."""
        self.disarms += 1
        self.armed = False


class ReplayLink(_QuietLink):
    """A vehicle whose telemetry is whatever the test sets (``state``), always fresh.

    ``clock`` is a one-element list (the monotonic time, s, the test moves); ``ranging``:
    ``(range_m, range_rate_mps)`` of a rangefinder, bumper to bumper, or None; ``sent``
    records ``(speed, heading)`` of each setpoint."""

    def __init__(self, clock: list[float]) -> None:
        super().__init__()
        self.clock = clock
        self.state: VehicleState | None = None
        self.ranging: tuple[float, float] | None = None
        self.sent: list[tuple[float, float]] = []

    def poll(self) -> Telemetry | None:
        """The set state as fresh telemetry (None before one is set)."""
        if self.state is None:
            return None
        now = self.clock[0]
        tel = Telemetry(self.state, 0.0, 0.0, "GUIDED", True, now, now)
        if self.ranging is not None:  # a rangefinder: bumper to bumper
            tel = replace(tel, range_m=self.ranging[0], range_rate_mps=self.ranging[1], t_range=now)
        return tel

    def prepare_and_arm(self, timeout_s: float, on_status: Any = None) -> None:
        """Armed (nothing to wait for)."""

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        """Recorded."""
        self.sent.append((speed_mps, heading_rad))
        return True

    def stop(self) -> bool:
        """Accepted."""
        return True

    def hold(self, timeout_s: float = 2.0) -> None:
        """Accepted."""

    def disarm(self, timeout_s: float = 2.0) -> None:
        """Accepted."""


class RecordingLink:
    """Delegates to a real link (a ``MavlinkLink``: its ``setpoints.last``); records
    ``(monotonic s, speed, heading)`` of every setpoint that actually went out
    (``setpoints.send``/``stop`` returned True), and the times of HOLDs and reconnects."""

    def __init__(self, link: Any) -> None:
        self._link = link
        self.sent: list[tuple[float, float, float]] = []
        self.holds: list[float] = []
        self.reconnects: list[float] = []
        self.setpoints = _RecordedSetpoints(link.setpoints, self.sent)
        self.modes = _RecordedModes(link.modes, self.holds)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)

    def reconnect(self, timeout_s: float) -> None:
        self.reconnects.append(time.monotonic())
        self._link.reconnect(timeout_s)

    def after(self, t: float) -> list[tuple[float, float, float]]:
        """The setpoints sent after monotonic time ``t``."""
        return [s for s in self.sent if s[0] > t]


class _RecordedSetpoints:
    """A link's ``setpoints``, each one that went out appended to ``sent``."""

    def __init__(self, setpoints: Any, sent: list[tuple[float, float, float]]) -> None:
        self._setpoints, self._sent = setpoints, sent

    def __getattr__(self, name: str) -> Any:
        return getattr(self._setpoints, name)

    def send(self, speed_mps: float, heading_rad: float) -> bool:
        ok = bool(self._setpoints.send(speed_mps, heading_rad))
        if ok:
            self._sent.append((time.monotonic(), float(speed_mps), float(heading_rad)))
        return ok

    def stop(self) -> bool:
        ok = bool(self._setpoints.stop())
        if ok and self._setpoints.last is not None:
            sp = self._setpoints.last
            self._sent.append((time.monotonic(), sp[0], sp[1]))
        return ok


class _RecordedModes:
    """A link's ``modes``, the time of each HOLD appended to ``holds``."""

    def __init__(self, modes: Any, holds: list[float]) -> None:
        self._modes, self._holds = modes, holds

    def __getattr__(self, name: str) -> Any:
        return getattr(self._modes, name)

    def hold(self, timeout_s: float = 2.0) -> None:
        self._holds.append(time.monotonic())
        self._modes.hold(timeout_s)


__all__ = ["FakeLink", "RecordingLink", "ReplayLink", "ScriptedLink"]
