"""MAVLink recordings (shared/sitl/*.jsonl.gz format) as plant-fitting data.

A recording is gzip (or plain) JSON Lines: a ``{"meta": ...}`` line, then one record per
MAVLink message sent (``dir`` ``tx``) or received (``rx``), with its time ``t`` (s). What the
vehicle did is read from GLOBAL_POSITION_INT (velocity, cm/s NED) and the ATTITUDE of the
same burst (yaw, rad NED): the signed forward speed is the velocity projected on the yaw.
With ``source="truth"`` a PX4 SIH recording's simulator state (HIL_STATE_QUATERNION on the
SIH link) is used instead. What it was told is read from SET_POSITION_TARGET_GLOBAL_INT /
_LOCAL_NED, decoded by the autopilot's own rules (shared/sitl/README.md §2,
shared/sitl-px4/README.md §2):

- ArduPilot, yaw field in use: heading = yaw; speed = |(vx, vy)|, reversing iff
  vx <= -FLT_EPSILON. Velocity only: heading = atan2(vy, vx), speed = |(vx, vy)|.
- PX4: heading = atan2(vy, vx), speed = |(vx, vy)|, the yaw field ignored, never reversing.

Setpoints the models cannot express (yaw rate, body frames, position targets) end a
segment. Only armed stretches with a steady setpoint stream are used: a gap longer than
``max_gap_s`` (the autopilots stop on their own after one) splits the data into segments.
Headings are returned in the project's convention (ENU, rad, 0 = east, counter-clockwise).
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openconvoy.core.errors import ConfigError, InputFileError

FLT_EPSILON = 1.1920929e-07
_SETPOINTS = ("SET_POSITION_TARGET_GLOBAL_INT", "SET_POSITION_TARGET_LOCAL_NED")
_NED_FRAMES = {1, 5, 6, 11}  # LOCAL_NED and the GLOBAL_* frames: vx, vy are north, east
_MAV_AUTOPILOT_PX4 = 12


@dataclass(frozen=True)
class Segment:
    """One stretch of a recording: measurements and the setpoints sent (times in s).

    Attributes:
        t, speed, heading: measurement times, signed forward speed (m/s), heading (ENU rad).
        t_cmd, cmd_speed, cmd_heading: setpoint send times, speed (m/s, negative =
            reverse), absolute heading (ENU rad).
    """

    t: np.ndarray
    speed: np.ndarray
    heading: np.ndarray
    t_cmd: np.ndarray
    cmd_speed: np.ndarray
    cmd_heading: np.ndarray


@dataclass(frozen=True)
class Recording:
    """A recording's usable segments and which autopilot made it (``ardupilot``/``px4``)."""

    path: Path
    autopilot: str
    segments: list[Segment]


def is_recording(path: str | Path) -> bool:
    """Whether ``path`` names a MAVLink recording (``.jsonl`` or ``.jsonl.gz``)."""
    name = Path(path).name
    return Path(path).is_file() and (name.endswith(".jsonl") or name.endswith(".jsonl.gz"))


def _ned_yaw_to_enu(yaw: float) -> float:
    return math.remainder(math.pi / 2 - yaw, 2 * math.pi)


def decode_setpoint(fields: dict, autopilot: str) -> tuple[float, float] | None:
    """(speed m/s, heading ENU rad) a velocity setpoint asks for, or None if the models
    cannot express it (position or yaw-rate targets, body frames)."""
    mask = int(fields.get("type_mask", 0))
    if mask & 0x38 or fields.get("coordinate_frame") not in _NED_FRAMES:
        return None  # velocity ignored, or not a north/east velocity
    vx, vy = float(fields["vx"]), float(fields["vy"])
    speed = math.hypot(vx, vy)
    if autopilot == "px4":
        return speed, _ned_yaw_to_enu(math.atan2(vy, vx))
    if not mask & 0x400:  # yaw in use: the nose at yaw, the sign of vx alone says reverse
        return (-speed if vx <= -FLT_EPSILON else speed), _ned_yaw_to_enu(float(fields["yaw"]))
    if not mask & 0x800:
        return None  # yaw rate: not a heading setpoint
    return speed, _ned_yaw_to_enu(math.atan2(vy, vx))


def _quat_yaw(q: list[float]) -> float:
    w, x, y, z = (float(c) for c in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def read_recording(
    path: str | Path, source: str = "telemetry", max_gap_s: float = 0.5
) -> Recording:
    """Read a recording's armed, steadily commanded stretches (see the module docstring)."""
    if source not in ("telemetry", "truth"):
        raise ConfigError(f"recording source must be telemetry or truth, got {source!r}")
    path = Path(path)
    opener = gzip.open if path.name.endswith(".gz") else open
    wanted = (
        "HEARTBEAT",
        "SET_POSITION_TARGET",
        'ATTITUDE"',
        "GLOBAL_POSITION_INT",
        "HIL_STATE_QUATERNION",
    )
    try:
        with opener(path, "rt") as f:
            # Parse only the message types used (a recording holds ~20 others).
            recs = [
                json.loads(line) for line in f if '"dir"' in line and any(w in line for w in wanted)
            ]
    except (OSError, ValueError) as exc:
        raise InputFileError(f"{path}: not a readable MAVLink recording ({exc})") from None
    autopilot = "ardupilot"
    for r in recs:
        if r["dir"] == "rx" and r.get("type") == "HEARTBEAT" and "link" not in r:
            autopilot = "px4" if r["fields"].get("autopilot") == _MAV_AUTOPILOT_PX4 else "ardupilot"
            break
    meas: list[tuple[float, float, float]] = []
    cmds: list[tuple[float, float, float] | tuple[float, None, None]] = []
    armed: list[tuple[float, bool]] = []
    yaw = None
    for r in recs:
        kind, fields = r.get("type"), r.get("fields", {})
        if r["dir"] == "tx" and kind in _SETPOINTS:
            sp = decode_setpoint(fields, autopilot)
            cmds.append((r["t"], *sp) if sp else (r["t"], None, None))
        elif r["dir"] != "rx":
            continue
        elif kind == "HEARTBEAT" and "link" not in r:
            armed.append((r["t"], bool(int(fields.get("base_mode", 0)) & 128)))
        elif source == "telemetry" and "link" not in r:
            if kind == "ATTITUDE":
                yaw = float(fields["yaw"])
            elif kind == "GLOBAL_POSITION_INT" and yaw is not None:
                vn, ve = fields["vx"] / 100.0, fields["vy"] / 100.0
                meas.append((r["t"], vn * math.cos(yaw) + ve * math.sin(yaw), _ned_yaw_to_enu(yaw)))
        elif source == "truth" and r.get("link") == "sih" and kind == "HIL_STATE_QUATERNION":
            y = _quat_yaw(fields["attitude_quaternion"])
            vn, ve = fields["vx"] / 100.0, fields["vy"] / 100.0
            meas.append((r["t"], vn * math.cos(y) + ve * math.sin(y), _ned_yaw_to_enu(y)))
    if not meas or not cmds:
        raise InputFileError(
            f"{path}: no {'telemetry' if source == 'telemetry' else 'SIH truth'} "
            "or no velocity setpoints in the recording"
        )
    return Recording(path, autopilot, _segments(meas, cmds, armed, max_gap_s))


def _segments(meas, cmds, armed, max_gap_s: float) -> list[Segment]:
    """Split into stretches of valid setpoints at most ``max_gap_s`` apart while armed."""
    m = np.array(meas, dtype=float)
    t_arm = np.array([a[0] for a in armed] or [0.0])
    is_armed = np.array([a[1] for a in armed] or [True])

    def armed_at(t: float) -> bool:
        k = int(np.searchsorted(t_arm, t, side="right")) - 1
        return bool(is_armed[k]) if k >= 0 else False

    runs: list[list[tuple[float, float, float]]] = []
    run: list[tuple[float, float, float]] = []
    for c in cmds:
        ok = c[1] is not None and armed_at(c[0])
        if not ok or (run and c[0] - run[-1][0] > max_gap_s):
            if len(run) > 1:
                runs.append(run)
            run = []
        if ok:
            run.append(c)
    if len(run) > 1:
        runs.append(run)
    out = []
    for run in runs:
        c = np.array(run, dtype=float)
        # Measurements from the first setpoint to one gap after the last one.
        sel = (m[:, 0] >= c[0, 0]) & (m[:, 0] <= c[-1, 0] + min(max_gap_s, 0.1))
        if sel.sum() < 20:
            continue
        out.append(Segment(m[sel, 0], m[sel, 1], m[sel, 2], c[:, 0], c[:, 1], c[:, 2]))
    return out
