"""Between a vehicle's controller and its autopilot: what the failsafes and the safety
envelope (``bridge.failsafes``) let through on one deploy tick.

The gate gathers what the failsafes read (link health, takeover, stop requests, the
convoy abort, position, the commanded speed, the gap and how fast it closes, the age of
the messages the member needs, the staleness ladder's stop, lateness), asks for their
verdict, says so in a status line when the reason changes, and turns the verdict into
the command sent: the envelope-capped drive, or speed 0 along the current heading.
"""

from __future__ import annotations

from collections.abc import Callable

from openconvoy.bridge.exchange import Exchange
from openconvoy.bridge.failsafes import DRIVE, Failsafes, TickInputs, Verdict
from openconvoy.bridge.intent import Want
from openconvoy.bridge.link import Telemetry, VehicleLink
from openconvoy.bridge.vehicle import HOLD_MODES
from openconvoy.core.member import ConvoyMember
from openconvoy.core.state import VehicleState


class SafetyGate:
    """The failsafes' say over one vehicle's commands.

    Args:
        failsafes: the failsafes and envelope.
        link: the vehicle link (its health and takeover).
        member: the convoy member (message ages, the staleness ladder's mode).
        exchange: V2V (the convoy abort).
        commanding: whether the run sends setpoints at all (read each tick).
        on_status: status lines.

    Attributes:
        last_reason: the latest verdict's reason ("" = none).
    """

    def __init__(
        self,
        failsafes: Failsafes,
        link: VehicleLink,
        member: ConvoyMember,
        exchange: Exchange,
        commanding: Callable[[], bool],
        on_status: Callable[[str], None],
    ) -> None:
        self.failsafes = failsafes
        self.link = link
        self.member = member
        self.exchange = exchange
        self._commanding = commanding
        self._on_status = on_status
        self.last_reason = ""

    def decide(
        self,
        clocks: tuple[float, float],
        tel: Telemetry,
        own: VehicleState,
        want: Want,
        *,
        waiting: bool,
        heading_cmd: float,
        gap: tuple[float, float],
        stop_requested: str,
        late_periods: float,
        ending: str = "",
    ) -> Verdict:
        """The verdict at (monotonic, wall) ``clocks`` (s) on ``want`` steered to
        ``heading_cmd`` (rad), with the (gap m, closing m/s) ahead; a status line when
        its reason changes."""
        now, wall = clocks
        following = self.member.vehicle_id != 0 and not waiting
        verdict = self.failsafes.decide(
            TickInputs(
                now=now,
                t_telemetry=tel.t_telemetry,
                t_heartbeat=tel.t_heartbeat,
                link_open=not self.link.lost,
                pilot_took_over=self._commanding() and self.link.modes.pilot_took_over,
                stop_requested=stop_requested,
                abort=self.exchange.abort,
                x=own.x,
                y=own.y,
                heading=heading_cmd,
                speed_cmd=want[0] if not waiting else 0.0,
                gap_m=gap[0],
                closing_mps=gap[1],
                needed_age_s=self.member.needed_age(wall) if following else 0.0,
                policy_error=want[3],
                stale_stop=following and self.member.mode == "stop",
                held=tel.mode in HOLD_MODES,
                late_periods=late_periods,
                ending=ending,
            )
        )
        if verdict.reason and verdict.reason not in (self.last_reason, ending):
            why = self.link.modes.takeover_reason if verdict.reason == "pilot took over" else ""
            self._on_status(
                f"vehicle {self.member.vehicle_id}: {verdict.reason}" + (f" ({why})" if why else "")
            )
        self.last_reason = verdict.reason
        return verdict

    def let_through(
        self, verdict: Verdict, want: Want, own: VehicleState, heading_cmd: float
    ) -> tuple[float, float, str]:
        """(speed m/s, heading rad, mode) sent: the drive capped by the envelope, or a
        stop along the current heading (mode ``failsafe`` or ``stop``)."""
        if verdict.command == DRIVE:
            return self.failsafes.envelope.cap(want[0]), heading_cmd, want[2]
        return 0.0, own.heading, "failsafe" if verdict.failsafe else "stop"
