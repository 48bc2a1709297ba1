"""Replay a firmware recording's commands into a simulated vehicle, over real MAVLink.

The recordings in shared/sitl and shared/sitl-px4 hold every message a recorder sent to
real ArduPilot/PX4 firmware (``tx``) and every message it got back (``rx``), with times.
``replay`` boots a ``SimVehicle`` with the recorded firmware's timing, sends it the same
``tx`` messages at the same times through a pymavlink UDP socket on loopback, and
records what comes back in the same format, so that one analysis can be applied to the
recording and to the simulation. The vehicle runs in lockstep with the recorder's clock
(``SimVehicle.advance``), as fast as the CPU allows.
"""

from __future__ import annotations

import gzip
import json
import math
import socket
from dataclasses import replace
from pathlib import Path
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.comms.geodesy import Origin

Record = dict[str, Any]
_SENT_TYPES = {
    "COMMAND_LONG",
    "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_POSITION_TARGET_LOCAL_NED",
    "PARAM_SET",
    "HEARTBEAT",
}


def load_recording(
    path: str | Path, rx_types: set[str] | None = None
) -> tuple[dict[str, Any], list[Record]]:
    """(meta, records) of a ``.jsonl.gz`` recording; with ``rx_types``, received messages
    of other types are skipped before they are parsed (``tx`` and ``mark`` always kept)."""
    records = []
    with gzip.open(path, "rt", encoding="utf-8") as f:
        meta = json.loads(f.readline())["meta"]
        for line in f:
            if rx_types is not None:
                kind = _rx_type(line)
                if kind is not None and kind not in rx_types:
                    continue
            records.append(json.loads(line))
    return meta, records


def _rx_type(line: str) -> str | None:
    """The ``type`` of a received-message line without parsing it (None for tx/mark)."""
    head = line[:120]
    if '"rx"' not in head:
        return None
    i = head.find('"type":')
    if i < 0:
        return None
    start = head.find('"', i + 7) + 1
    return head[start : head.find('"', start)]


def _home(meta: dict[str, Any]) -> tuple[Origin, float]:
    """(home, start heading in compass degrees) from a recording's ``meta.home``."""
    home = meta["home"]
    if isinstance(home, dict):
        return Origin(float(home["lat"]), float(home["lon"]), float(home.get("alt", 0.0))), float(
            home.get("heading_deg", 0.0)
        )
    lat, lon, alt, heading = (float(v) for v in str(home).split(","))
    return Origin(lat, lon, alt), heading


def boot_time(meta: dict[str, Any], records: list[Record]) -> float:
    """Recorder time (s) at which the autopilot booted."""
    if "t_px4_started" in meta:
        return float(meta["t_px4_started"])
    offsets = [
        r["t"] - r["fields"]["time_boot_ms"] / 1000.0
        for r in records
        if r["dir"] == "rx" and "time_boot_ms" in r.get("fields", {})
    ]
    return min(offsets) if offsets else 0.0


def _fields(fields: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in fields.items():
        if v == "nan":
            v = math.nan
        elif isinstance(v, str):
            v = v.encode()
        out[k] = v
    return out


def replay_config(
    meta: dict[str, Any], records: list[Record], **overrides: Any
) -> SimVehicleConfig:
    """The simulated vehicle a recording's firmware corresponds to (firmware timing)."""
    home, heading_deg = _home(meta)
    sysid = next(
        r["fields"]["target_system"]
        for r in records
        if r["dir"] == "tx" and "target_system" in r["fields"]
    )
    px4 = "t_px4_started" in meta
    config = SimVehicleConfig(
        system_id=int(sysid),
        autopilot="px4" if px4 else "ardupilot",
        home=home,
        start_heading_rad=math.radians(90.0 - heading_deg),
        timing="firmware",
    )
    return replace(config, **overrides)


def replay(
    meta: dict[str, Any],
    records: list[Record],
    step_s: float = 0.02,
    rx_types: set[str] | None = None,
    **overrides: Any,
) -> list[Record]:
    """Send the recording's ``tx`` messages to a simulated vehicle at their times and return
    what it sent back, as records (``t`` = the recorder's clock), plus the ``mark``s.
    ``rx_types``: decode and keep only these message types (the rest is received and
    dropped by message id, unparsed)."""
    config = replay_config(meta, records, **overrides)
    t_boot = boot_time(meta, records)
    vehicle, gcs = _open_pair(meta, config)
    mav = mp.mav()
    keep_ids = None
    if rx_types is not None:
        keep_ids = {cls.id for cls in mav.mavlink_map.values() if cls.msgname in rx_types}
    sock = gcs.port
    sent = [r for r in records if r["dir"] == "tx" and r["type"] in _SENT_TYPES]
    out: list[Record] = [r for r in records if r["dir"] == "mark"]
    end = float(meta.get("duration_s") or records[-1]["t"])
    i = 0
    n_steps = int(math.ceil(end / step_s))
    try:
        for k in range(n_steps + 1):
            t = k * step_s
            any_sent = False
            while i < len(sent) and sent[i]["t"] <= t:
                r = sent[i]
                cls = getattr(mav, f"MAVLink_{r['type'].lower()}_message")
                gcs.mav.send(cls(**_fields(r["fields"])))
                any_sent = True
                i += 1
            if t < t_boot:
                continue
            if any_sent:
                vehicle.wait_readable(0.05)
            vehicle.advance_to(t - t_boot)
            out.extend(_as_record(msg, t) for msg in _receive(gcs, sock, keep_ids))
    finally:
        gcs.close()
        vehicle.close()
    out.sort(key=lambda r: r["t"])
    return out


def _open_pair(meta: dict[str, Any], config: SimVehicleConfig) -> tuple[SimVehicle, Any]:
    """A lockstep simulated vehicle on a free local UDP port, and the recorder's side of
    the link (the recording's own MAVLink ids)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", config).open()
    gcs = mp.mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{port}",
        source_system=int(meta.get("source_system", 255)),
        source_component=int(meta.get("source_component", 190)),
    )
    return vehicle, gcs


def _as_record(msg: Any, t: float) -> Record:
    """A received message as a recording's ``rx`` record at recorder time ``t`` (s)."""
    d = msg.to_dict()
    d.pop("mavpackettype", None)
    return {
        "t": t,
        "dir": "rx",
        "type": msg.get_type(),
        "src": [msg.get_srcSystem(), msg.get_srcComponent()],
        "fields": d,
    }


def _receive(gcs: Any, sock: socket.socket, keep_ids: set[int] | None) -> list[Any]:
    """Every datagram waiting on the recorder's socket (one MAVLink 2 message each, as
    pymavlink sends them), decoded by pymavlink when its id is wanted."""
    out: list[Any] = []
    while True:
        try:
            data, _ = sock.recvfrom(65535)
        except BlockingIOError:
            return out
        if len(data) < 10 or data[0] != 0xFD:
            continue
        if keep_ids is not None and (data[7] | data[8] << 8 | data[9] << 16) not in keep_ids:
            continue
        for msg in gcs.mav.parse_buffer(data) or []:
            if msg.get_type() != "BAD_DATA":
                out.append(msg)
