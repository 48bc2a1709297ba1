"""Field tools behind ``openconvoy bsm listen | send | decode``.

``listen`` prints every BSM (and compatibility message) heard on a group, one line each,
whoever sent it; with a convoy's keys (``--convoy``) it verifies signed SPDUs and prints,
per sender, the frames accepted and rejected by reason, and a summary at exit. ``send``
sends test BSMs from a made-up vehicle moving at constant speed and heading, signed with
``--key`` or not, or replays a captured datagram, at any rate (a forger's or a flood's
tool, for resilience experiments). ``decode`` prints one frame's core fields in physical
units. ``listen`` and ``send`` speak IPv6 multicast, or with ``ros2`` = (topic, DDS domain)
the ROS 2 topic a convoy with ``[v2v] transport = "ros2"`` carries the same bytes on
(``comms.dds``). The argparse declarations live in ``openconvoy.comms.cli`` (``_add_bsm``); these
functions do the work.
"""

from __future__ import annotations

import json
import logging
import math
import select
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.mapping import reconstruct_send_time, state_to_core
from openconvoy.comms.multicast import Datagram, Ipv4Multicast, Ipv6Multicast, interface_index
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import derive_temp_id, parse_temp_id
from openconvoy.core.errors import ConfigError, LinkError
from openconvoy.core.state import VehicleState

log = logging.getLogger(__name__)

#: Temporary ID of ``bsm send`` unless ``--id`` is given.
DEFAULT_SEND_ID = derive_temp_id("bsm-send", 0)
#: The DDS samples ``listen`` keeps between reads: larger than a vehicle's (``dds.depth_for``),
#: since a field tool prints every message rather than acting on the newest.
LISTEN_DEPTH = 1024
#: How long ``send`` over DDS waits for discovery to match a reader before the first BSM
#: (s): best-effort samples written before are lost to it (as ``v2v.send_abort`` waits).
ROS2_WAIT_S = 3.0
#: Then how long it lets the reader's side of discovery catch up (s): our writer knowing a
#: reader is half of it, and Cyclone's readers "only accept data from discovered writers"
#: (its manual, "Proxy participants and endpoints").
ROS2_SETTLE_S = 0.5
#: ``vehicle_id`` stamped on the tools' DDS samples: not a convoy member (0..254) nor the
#: operator's abort (-1).
TOOL_VEHICLE_ID = -2


def require_codec() -> None:
    """Compile the J2735 codec now; ``ValueError`` (one CLI line) if asn1tools is missing."""
    try:
        j.warm_up()
    except ModuleNotFoundError as exc:
        raise ConfigError(str(exc)) from None


def _fmt(v: float | None, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


class Tally:
    """Per sender: frames accepted and rejected by reason (``listen``'s summary)."""

    def __init__(self) -> None:
        self.accepted: dict[str, int] = {}
        self.rejected: dict[str, dict[str, int]] = {}

    def accept(self, sender: str) -> None:
        self.accepted[sender] = self.accepted.get(sender, 0) + 1

    def reject(self, sender: str, reason: str) -> None:
        by = self.rejected.setdefault(sender, {})
        by[reason] = by.get(reason, 0) + 1

    def lines(self) -> list[str]:
        """One line per sender, then the total."""
        out = []
        for sender in sorted(set(self.accepted) | set(self.rejected)):
            by = self.rejected.get(sender, {})
            reasons = " ".join(f"{r}={n}" for r, n in sorted(by.items()))
            out.append(
                f"{sender}: accepted {self.accepted.get(sender, 0)}, rejected "
                f"{sum(by.values())}" + (f" ({reasons})" if reasons else "")
            )
        n_ok = sum(self.accepted.values())
        n_bad = sum(sum(by.values()) for by in self.rejected.values())
        out.append(
            f"summary: {n_ok} accepted, {n_bad} rejected from "
            f"{len(set(self.accepted) | set(self.rejected))} senders"
        )
        return out


def _unsigned_sender(data: bytes) -> str:
    if data[:2] == j.BSM_FRAME_PREFIX:
        try:
            return f"id {j.decode_frame(data).core.temp_id.hex().upper()} (unsigned)"
        except j.BsmDecodeError:
            return "malformed"
    try:
        return f"car {cj.decode(data).car} (unsigned)"
    except cj.CompatDecodeError:
        return "malformed"


def verify_datagram(data: bytes, t_rx: float, auth: Authenticator, tally: Tally) -> str:
    """``listen --convoy``'s line for one datagram: the message, prefixed by its verified
    signer, or ``REJECTED <reason>``; counted in ``tally``."""
    if not sp.is_signed(data):
        sender = _unsigned_sender(data)
        reason = "malformed" if sender == "malformed" else "unsigned"
        tally.reject(sender, reason)
        return f"REJECTED {reason}: {sender}"
    try:
        spdu = sp.decode_signed(data)
    except sp.SpduDecodeError as exc:
        tally.reject("malformed", "malformed")
        return f"REJECTED malformed: {exc}"
    cert = auth.check(spdu, t_rx)
    known = auth.known(spdu.digest)
    sender = known.name if known is not None else f"digest {spdu.digest.hex()}"
    if isinstance(cert, str):
        tally.reject(sender, cert)
        return f"REJECTED {cert}: {sender}"
    msg_cnt = None
    if spdu.psid == c.PSID_ABORT:
        line = "ABORT"
    else:
        described = describe_datagram(spdu.payload, t_rx)
        if described is None:
            tally.reject(sender, "malformed")
            return f"REJECTED malformed: {sender}"
        msg_cnt = j.decode_frame(spdu.payload).core.msg_cnt
        line = described
    refused = auth.admit(spdu, t_rx, msg_cnt)
    if refused is not None:
        tally.reject(sender, refused)
        return f"REJECTED {refused}: {sender}"
    tally.accept(sender)
    return f"[{cert.name}] {line}"


def describe_datagram(data: bytes, t_rx: float) -> str | None:
    """One ``listen`` line for a datagram received at ``t_rx`` (None if not a message).

    J2735: ``id=0A1B2C3D cnt= 12 lat=28.6024000 lon=-81.2001000 speed=1.00 m/s
    heading=90.0000 deg age=0.012 s``; compatibility messages show ``car=N`` instead of
    the id and count, and ``ABORT`` when the abort flag is set.
    """
    if data[:2] == j.BSM_FRAME_PREFIX:
        try:
            msg = j.decode_frame(data)
        except j.BsmDecodeError as exc:
            log.debug("not a BSM: %s", exc)
            return None
        p = j.to_physical(msg.core)
        age = t_rx - reconstruct_send_time(msg.core.sec_mark, t_rx)
        extra = ""
        if msg.part_ii_ids or msg.regional_ids:
            extra = f" partII={list(msg.part_ii_ids)} regional={list(msg.regional_ids)}"
        return (
            f"id={p['temp_id']} cnt={msg.core.msg_cnt:3d} "
            f"lat={_fmt(p['lat_deg'], '.7f')} lon={_fmt(p['lon_deg'], '.7f')} "
            f"speed={_fmt(p['speed_mps'], '.2f')} m/s heading={_fmt(p['heading_deg'], '.4f')} deg "
            f"age={age:.3f} s{extra}"
        )
    if data.lstrip()[:1] == b"{":
        try:
            m = cj.decode(data)
        except cj.CompatDecodeError as exc:
            log.debug("not a compatibility message: %s", exc)
            return None
        age = max(0.0, t_rx - m.t)
        return (
            f"car={m.car} (compat) lat={_fmt(m.lat_deg, '.7f')} lon={_fmt(m.lon_deg, '.7f')} "
            f"speed={m.speed:.2f} m/s heading={m.heading_deg:.4f} deg age={age:.3f} s"
            + (" ABORT" if m.abort else "")
        )
    log.debug("ignored a datagram of %d bytes: neither J2735 nor JSON", len(data))
    return None


def listen(
    iface: str,
    *,
    group: str,
    port: int,
    compat_enabled: bool = False,
    count: int | None = None,
    timeout_s: float | None = None,
    out: TextIO = sys.stdout,
    clock: Callable[[], float] = time.time,
    auth: Authenticator | None = None,
    ros2: tuple[str, int] | None = None,
) -> int:
    """Print messages heard on ``iface`` until ``count`` messages or ``timeout_s`` seconds.

    With ``security.auth`` (a verifier holding the convoy's authority certificate) every datagram
    is verified and its line says so, and a per-sender summary is printed at the end,
    Ctrl-C included. With ``ros2`` = (ROS 2 topic, DDS domain id) the messages are read from
    that topic instead of the multicast group (Cyclone kept on ``iface``; no compatibility
    format there). Returns the number of messages printed.
    """
    _check_ros2(ros2, compat_enabled, None)
    require_codec()
    tally = Tally()
    socks: list[Any] = [_open(iface, group, port, 1, ros2, LISTEN_DEPTH)]
    if compat_enabled:
        socks.append(Ipv4Multicast(iface))
    printed = 0
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        while count is None or printed < count:
            wait = 0.5 if deadline is None else deadline - time.monotonic()
            if wait <= 0:
                break
            ready = _ready(socks, min(wait, 0.5), ros2 is not None)
            now = clock()
            for s in ready:
                dgram: Datagram
                for dgram in s.recv_all():
                    if auth is not None:
                        line: str | None = verify_datagram(dgram.data, now, auth, tally)
                    else:
                        line = describe_datagram(dgram.data, now)
                    if line is None:
                        continue
                    print(line, file=out, flush=True)
                    printed += 1
                    if count is not None and printed >= count:
                        return printed
    finally:
        for s in socks:
            s.close()
        if auth is not None:
            print("\n".join(tally.lines()), file=out, flush=True)
    return printed


def send(
    iface: str,
    *,
    group: str,
    port: int,
    hop_limit: int = 1,
    count: int = 10,
    rate_hz: float = 10.0,
    lat_deg: float,
    lon_deg: float,
    elev_m: float = 0.0,
    speed_mps: float = 0.0,
    heading_deg: float = 0.0,
    temp_id: bytes = DEFAULT_SEND_ID,
    compat_car: int | None = None,
    clock: Callable[[], float] = time.time,
    sleep: Callable[[float], None] = time.sleep,
    auth: Authenticator | None = None,
    frame: bytes | None = None,
    ros2: tuple[str, int] | None = None,
    ros2_wait_s: float = ROS2_WAIT_S,
) -> int:
    """Send ``count`` test BSMs at ``rate_hz`` from a vehicle starting at ``lat_deg``,
    ``lon_deg`` and moving at ``speed_mps`` along compass ``heading_deg``.

    With ``compat_car`` set, each state also goes out as a compatibility message from that
    convoy position on the IPv4 group. With ``security.auth`` each BSM is a signed SPDU. With
    ``frame`` that datagram is sent as it is, ``count`` times (a replay). With ``ros2`` =
    (ROS 2 topic, DDS domain id) the datagrams go on that topic instead of the group, once
    DDS discovery has matched a reader or ``ros2_wait_s`` (s) has passed (Cyclone kept on
    ``iface``; no compatibility format there). Returns the number of BSMs sent.
    """
    _check_ros2(ros2, False, compat_car)
    if count < 0:
        raise ConfigError(f"--count must be >= 0, got {count}")
    if not rate_hz > 0:
        raise ConfigError(f"--rate must be > 0 Hz, got {rate_hz}")
    require_codec()
    start = Origin(lat_deg, lon_deg, elev_m)
    heading_enu = math.radians(90.0 - heading_deg)
    sock = _open(iface, group, port, hop_limit, ros2, read=False)
    sock4 = Ipv4Multicast(iface) if compat_car is not None else None
    if ros2 is not None:
        if sock.wait_for_readers(ros2_wait_s) == 0:
            log.warning("no reader of %s on DDS domain %d yet: sending anyway", *ros2)
        else:
            sleep(ROS2_SETTLE_S)
    t0 = clock()
    try:
        for k in range(count):
            if k:
                sleep(max(0.0, t0 + k / rate_hz - clock()))
            now = clock()
            vehicle_id = 0 if compat_car is None else compat_car
            state = _straight_line(vehicle_id, now - t0, now, speed_mps, heading_enu)
            data = frame if frame is not None else _bsm(state, start, temp_id, k, auth)
            try:
                sock.send(data)
            except OSError as exc:
                raise LinkError(f"--iface {iface}: cannot send: {exc.strerror or exc}") from None
            if frame is not None:
                continue
            if sock4 is not None:
                sock4.send(cj.encode_state(state, start))
    finally:
        sock.close()
        if sock4 is not None:
            sock4.close()
    return count


def _check_ros2(ros2: tuple[str, int] | None, compat: bool, compat_car: int | None) -> None:
    """``ConfigError`` if the compatibility format is asked for over ROS 2 (it is IPv4
    multicast only, as the original implementation)."""
    if ros2 is not None and (compat or compat_car is not None):
        flag = "--compat" if compat else "--compat-car"
        raise ConfigError(f"{flag}: the original JSON format is IPv4 multicast only, not ros2")


def _open(
    iface: str,
    group: str,
    port: int,
    hop_limit: int,
    ros2: tuple[str, int] | None,
    depth: int | None = None,
    read: bool = True,
) -> Any:
    """The J2735 link: the IPv6 multicast socket, or with ``ros2`` = (topic, domain) a
    ``comms.dds.DdsTransport`` stamping ``TOOL_VEHICLE_ID`` and keeping ``depth`` samples
    (default: a vehicle's; none without ``read``). An unknown ``iface`` is the same one
    line either way."""
    if ros2 is None:
        return Ipv6Multicast(iface, group, port, hop_limit)
    from openconvoy.comms.dds import DEPTH, DdsTransport, dds_topic

    topic, domain = ros2
    dds_topic(topic)  # a bad name first, as a flag's error
    interface_index(iface)  # Cyclone's own refusal would blame the domain id
    return DdsTransport(
        iface, topic, domain, vehicle_id=TOOL_VEHICLE_ID, depth=depth or DEPTH, read=read
    )


def _ready(links: list[Any], timeout_s: float, dds: bool) -> list[Any]:
    """The links with datagrams waiting, after at most ``timeout_s`` (s): ``select`` on
    sockets, the DDS transport's own wait set (``DdsTransport.wait``, the only link then)."""
    if dds:
        (link,) = links
        return [link] if link.wait(timeout_s) else []
    ready, _, _ = select.select(links, [], [], timeout_s)
    return ready


def _straight_line(
    vehicle_id: int, elapsed_s: float, now: float, speed_mps: float, heading_enu: float
) -> VehicleState:
    """The test vehicle ``elapsed_s`` after starting at the ENU origin at ``speed_mps``
    along ``heading_enu`` (rad), stamped ``now``."""
    d = speed_mps * elapsed_s
    return VehicleState(
        vehicle_id,
        now,
        d * math.cos(heading_enu),
        d * math.sin(heading_enu),
        speed_mps,
        heading_enu,
    )


def _bsm(
    state: VehicleState, start: Origin, temp_id: bytes, k: int, auth: Authenticator | None
) -> bytes:
    """The ``k``-th test BSM's datagram for ``state`` (signed at ``state.t`` with ``security.auth``);
    the elevation is the start's."""
    core = state_to_core(state, start, temp_id, k % 128, alt_m=start.alt_m)
    data = j.encode_frame(core)
    return data if auth is None else auth.sign(data, c.PSID_BSM, state.t)


def parse_hex(text: str) -> bytes:
    """Bytes from hex text, tolerating spaces, colons and a ``0x`` prefix."""
    cleaned = "".join(text.split()).replace(":", "")
    cleaned = cleaned[2:] if cleaned.lower().startswith("0x") else cleaned
    try:
        return bytes.fromhex(cleaned)
    except ValueError:
        raise ConfigError(f"not hexadecimal: {text[:40]!r}") from None


def decode_lines(data: bytes, *, as_json: bool = False) -> list[str]:
    """``decode``'s output for one frame: ``name: value`` lines, or one JSON line.

    Raises ``ValueError`` (``BsmDecodeError``) if ``data`` is not a valid BSM frame.
    """
    require_codec()
    msg = j.decode_frame(data)
    fields: dict[str, Any] = j.to_physical(msg.core)
    fields["part_ii_ids"] = list(msg.part_ii_ids)
    fields["regional_ids"] = list(msg.regional_ids)
    if as_json:
        return [json.dumps(fields)]
    width = max(len(k) for k in fields)
    out = []
    for k, v in fields.items():
        if isinstance(v, float):
            v = str(round(v, 7))  # J2735's finest unit is 1e-7 degree
        elif v is None:
            v = "unavailable"
        out.append(f"{k:<{width}}  {v}")
    return out


def temp_id_arg(text: str) -> bytes:
    """argparse type for ``--id``: 8 hex digits."""
    return parse_temp_id(text)
