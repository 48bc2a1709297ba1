"""The deploy runner's record of a run: one log row per tick (``openconvoy.logs``' columns
plus ``EXTRA_COLUMNS``), status lines, and the metadata JSON (``vehicle_N.json``), written
through ``bridge.recorder.RunRecorder``. It reads the runner's parts; it decides nothing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from openconvoy.bridge.link import Telemetry
from openconvoy.bridge.recorder import RunRecorder
from openconvoy.core.state import VehicleState

if TYPE_CHECKING:
    from openconvoy.bridge.runner import DeployRunner

EXTRA_COLUMNS = ("length_m", "msgs_kept", "loop_overruns", "telemetry_age_s", "telemetry_valid")
"""Numeric log columns after DESIGN.md's: the vehicle's length (as ``sim`` writes, so
``report`` counts collisions from the log alone), the messages the Rx gate kept, the loop
overruns so far, and how old the telemetry behind the row was (s; ``fit-plant`` removes it
from the fitted actuation delay). As in ``sim``, ``msgs_received``/``msgs_lost`` count what the link
delivered / the loss model dropped, before the Rx gate. Why a failsafe fired goes to the
metadata JSON (``failsafe_events``)."""


class RunLog:
    """A run's log file, status lines and metadata.

    Args:
        log_dir: directory for ``vehicle_N.csv`` / ``.json``; None = no files.
        vehicle_id: convoy index.
        status_period_s: status line period (s); 0 = none.
        on_status: receives status lines.
    """

    def __init__(
        self,
        log_dir: Path | None,
        vehicle_id: int,
        status_period_s: float,
        on_status: Callable[[str], None],
    ) -> None:
        self.recorder = RunRecorder(log_dir, vehicle_id, EXTRA_COLUMNS)
        self.applies_loss: bool | None = None  # learnt from the V2V metadata at the first row
        self.status_period_s = status_period_s
        self.on_status = on_status
        self._t_status = -math.inf

    def row(
        self,
        r: DeployRunner,
        wall: float,
        own: VehicleState,
        tel: Telemetry,
        speed: float,
        change: float,
        mode: str,
        gap: float,
        sent: bool,
        valid: bool = True,
    ) -> None:
        """This tick's row: what was measured (NaN when the telemetry is not ``valid``:
        lost, not repeated), and what was commanded (NaN if nothing went out)."""
        if not self.recorder.recording:
            return
        m, vid, frame = r.member, r.options.vehicle_id, r.frame
        nan = math.nan
        if self.applies_loss is None:
            self.applies_loss = applies_loss(_safe(lambda: r.v2v.metadata) or {})
        # A vehicle whose V2V applies no loss model writes -1 ("not logged") for what was
        # delivered and lost: the delivery ratio is over the links that apply loss (a
        # lossless leader's 100 % would raise the followers' 70 % to 80 %).
        lossy = self.applies_loss
        if not self.recorder.row(
            {
                "t_s": wall,
                "vehicle_id": vid,
                "x_m": own.x if valid else nan,
                "y_m": own.y if valid else nan,
                "lat_deg": tel.lat_deg if valid else nan,
                "lon_deg": tel.lon_deg if valid else nan,
                "speed_mps": own.speed if valid else nan,
                "heading_rad": own.heading if valid else nan,
                "accel_mps2": own.accel if valid else nan,
                "cmd_speed_mps": speed if sent else math.nan,
                "cmd_heading_change_rad": change if sent else math.nan,
                "mode": mode,
                "gap_m": gap,
                "desired_gap_m": frame.desired_gap_m,
                "spacing_error_m": frame.spacing_error_m,
                "msgs_sent": m.msgs_sent,
                "msgs_received": r.exchange.delivered() if lossy else -1,
                "msgs_lost": r.v2v.counters.lost if lossy else -1,
                "pred_msg_age_s": frame.pred_msg_age_s,
                "length_m": m.lengths[vid],
                "msgs_kept": m.msgs_received,
                "loop_overruns": r.timer.overruns if r.timer else 0,
                "telemetry_age_s": max(wall - own.t, 0.0),
                "telemetry_valid": int(valid),
            }
        ):
            self.on_status(
                f"vehicle {vid}: log write failed ({self.recorder.failed}): stopping the "
                "vehicle; the log ends here, its metadata is still written"
            )

    def status(
        self,
        r: DeployRunner,
        now: float,
        own: VehicleState,
        mode: str,
        gap: float,
        valid: bool = True,
    ) -> None:
        """A status line every ``status_period_s`` (without telemetry: how long none came,
        not the last speed)."""
        p = self.status_period_s
        if p <= 0 or now - self._t_status < p:
            return
        self._t_status = now
        m = r.member
        tel = r.vehicle.tel
        if valid or tel is None:
            motion = f"v {own.speed:4.2f} m/s"
        else:
            motion = f"no telemetry for {max(0.0, now - tel.t_telemetry):.1f} s"
        parts = [f"vehicle {r.options.vehicle_id}", mode, motion]
        if not r.is_leader:
            parts.append(f"gap {gap:5.2f} m (want {r.frame.desired_gap_m:4.1f})")
            parts.append(f"age {r.frame.pred_msg_age_s:4.2f} s")
        parts.append(f"tx {m.msgs_sent} rx {m.msgs_received}")
        self.on_status(" | ".join(parts))

    def close(self, r: DeployRunner, reason: str, code: int) -> None:
        """Flush and close the log with the run's metadata (nothing when it was never
        opened); a file that cannot be written is one status line, never an exception."""
        if not self.recorder.created:
            return
        why = self.recorder.close(metadata(r, reason, code))
        if why:
            self.on_status(f"vehicle {r.options.vehicle_id}: log not fully saved ({why})")


def metadata(r: DeployRunner, reason: str, code: int = 0) -> dict[str, Any]:
    """The run's metadata (``vehicle_N.json``)."""
    o, timer, link, v2v = r.options, r.timer, r.link, r.v2v
    wall0 = r.wall() - r.clock()  # maps monotonic event times to the shared clock
    return {
        "kind": "deploy",
        "vehicle_id": o.vehicle_id,
        "n_vehicles": r.convoy.n_vehicles,
        "convoy": r.convoy.name,
        "scenario": r.convoy.scenario,
        "policy": r.policy.name,
        "rate_hz": o.rate_hz,
        "dry_run": o.dry_run,
        "passive": o.passive,
        "autopilot": r.vehicle.autopilot or _safe(lambda: link.autopilot),
        "stay_armed": o.stay_armed,
        "uncommanded_motion": r.vehicle.uncommanded or None,
        "telemetry_rates_hz": link.telemetry_rates,
        "v2v": _safe(lambda: v2v.metadata) or {},
        "t_begin_s": r.t_begin_wall,
        "t_start_s": r.start_gate.t_start_wall,
        "t_end_s": r.wall(),
        "exit_reason": reason,
        "exit_code": code,
        "takeover_reason": link.modes.takeover_reason or None,
        "broadcast_paused": [
            {"from_s": a, "to_s": b, "why": "autopilot link lost"}
            for a, b in r.exchange.broadcast_pauses
        ],
        "ticks": timer.ticks if timer else 0,
        "overruns": timer.overruns if timer else 0,
        "late_ticks": timer.late_ticks if timer else 0,
        "max_tick_late_s": timer.max_late_s if timer else 0.0,
        "v2v_counters": _safe(lambda: asdict(v2v.counters)),
        "policy_errors": r.failsafes.policy_errors,
        "policy_act_s": _act_times(r),
        "failsafe_events": [{"t_s": wall0 + t, "reason": why} for t, why in r.failsafes.events],
        "msgs_sent": r.member.msgs_sent,
        "msgs_received": r.exchange.delivered(),
        "msgs_kept": r.member.msgs_received,
        "msgs_lost": v2v.counters.lost,
        **r.metadata_extra,
    }


def _act_times(r: DeployRunner) -> dict[str, float] | None:
    """The follower policy's ``act`` durations (s): calls, median, p99, max (None: none)."""
    guard = r.intent.guard
    if guard is None or not guard.times:
        return None
    import numpy as np

    t = np.array(guard.times)
    return {
        "calls": float(len(t)),
        "median": float(np.median(t)),
        "p99": float(np.percentile(t, 99)),
        "max": float(t.max()),
    }


def applies_loss(v2v_metadata: dict[str, Any]) -> bool:
    """Whether a V2V endpoint emulates loss, from its metadata (``comms.v2v.V2V``: a
    ``loss`` entry; ``bridge.localv2v.LocalV2V``: ``per`` > 0)."""
    if "loss" in v2v_metadata:
        return bool(v2v_metadata["loss"])
    return float(v2v_metadata.get("per") or 0.0) > 0.0


def _safe(fn: Callable[[], Any]) -> Any:
    try:
        return fn()
    except Exception:  # noqa: BLE001
        return None
