"""MAVLink recordings of real firmware read as fitting data: the setpoints decoded by each
autopilot's rules agree with what the firmware then did."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.experiments.recording import decode_setpoint, is_recording, read_recording

REPO_ROOT = Path(__file__).resolve().parents[2]
SITL = REPO_ROOT / "tests" / "data" / "sitl"
SITL_PX4 = REPO_ROOT / "tests" / "data" / "sitl-px4"


def _shared(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    return path


def _phases(path: Path) -> list[tuple[float, dict]]:
    with gzip.open(path, "rt") as f:
        return [(r["t"], r["fields"]) for r in map(json.loads, f) if r.get("dir") == "mark"]


def test_decoded_ardupilot_setpoints_match_what_the_firmware_did() -> None:
    """Every 2503 (body and NED encodings, 8 headings, 89.99/90.01) and 3527 case of
    setpoint_semantics: the decoded speed's sign and the decoded heading are what the
    firmware drove (mean signed speed and heading over the last 3 s of each 6 s case)."""
    path = _shared(SITL / "setpoint_semantics.jsonl.gz")
    rec = read_recording(path)
    assert rec.autopilot == "ardupilot"
    t = np.concatenate([s.t for s in rec.segments])
    speed = np.concatenate([s.speed for s in rec.segments])
    heading = np.concatenate([s.heading for s in rec.segments])
    t_cmd = np.concatenate([s.t_cmd for s in rec.segments])
    cmd_v = np.concatenate([s.cmd_speed for s in rec.segments])
    cmd_h = np.concatenate([s.cmd_heading for s in rec.segments])
    cases = [(t0, f) for t0, f in _phases(path) if f.get("mask") in (2503, 3527)]
    assert len(cases) == 24  # 8 body + 10 NED (incl. 89.99 / 90.01) + 4 velocity-only + 2 reverse
    reversing = []
    for t0, f in cases:
        sel = (t > t0 + 3.0) & (t < t0 + 6.0)
        k = np.searchsorted(t_cmd, t0 + 3.0)
        v, h = float(cmd_v[k]), float(cmd_h[k])
        got = float(np.mean(speed[sel]))
        assert math.copysign(1.0, got) == math.copysign(1.0, v), f["name"]
        assert abs(got) == pytest.approx(abs(v), abs=0.1), f["name"]
        assert (
            math.degrees(abs(math.remainder(float(np.mean(heading[sel])) - h, 2 * math.pi))) < 2.0
        )
        if v < 0:
            reversing.append(f["name"])
    # The firmware's rule: NED vx <= -FLT_EPSILON reverses (README §2), plus deliberate reverses.
    assert reversing == [
        "ned_h135",
        "ned_h180",
        "ned_h225",
        "ned_h90.01",
        "reverse_yaw_current",
        "reverse_yaw_plus90",
    ]


def test_px4_setpoints_ignore_yaw_and_never_reverse() -> None:
    south = {"type_mask": 2503, "coordinate_frame": 1, "vx": -1.0, "vy": 0.0, "yaw": 0.0}
    speed, heading = decode_setpoint(south, "px4")
    assert speed == 1.0 and math.degrees(heading) == pytest.approx(-90.0)
    ardupilot_speed, ardupilot_heading = decode_setpoint(south, "ardupilot")
    assert ardupilot_speed == -1.0 and math.degrees(ardupilot_heading) == pytest.approx(90.0)
    # Yaw-rate and body-frame setpoints are not heading setpoints: they end a segment.
    assert decode_setpoint(dict(south, type_mask=1479), "ardupilot") is None
    assert decode_setpoint(dict(south, coordinate_frame=8), "px4") is None


def test_px4_recording_reads_the_sih_truth() -> None:
    path = _shared(SITL_PX4 / "speed_steps.jsonl.gz")
    assert is_recording(path)
    truth = read_recording(path, source="truth")
    assert truth.autopilot == "px4"
    (seg,) = truth.segments
    # 0.5 m/s from standstill never moves the SIH rover (README §3; the EKF reads 0.1-0.55).
    t0 = next(t for t, f in _phases(path) if f.get("speed") == 0.5)
    sel = (seg.t > t0) & (seg.t < t0 + 8.0)
    assert np.abs(seg.speed[sel]).max() < 0.05
    assert np.isin(
        np.round(seg.cmd_speed, 3), [0.001, 0.5, 0.7, 0.8, 0.9, 1.0, 2.0, 3.0, 5.0]
    ).all()


def test_a_file_that_is_not_a_recording_is_one_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.jsonl.gz"
    bad.write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="not a readable MAVLink recording"):
        read_recording(bad)
    empty = tmp_path / "empty.jsonl"
    empty.write_text('{"meta": {}}\n')
    with pytest.raises(ValueError, match="no telemetry"):
        read_recording(empty)
