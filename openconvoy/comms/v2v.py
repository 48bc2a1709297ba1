"""The V2V link a convoy member uses on a real vehicle: send own state, poll others'.

``V2V`` is the facade the vehicle bridge plugs in::

    link = V2V(LinkConfig(iface="wlan0"), TempIds("lab", 3), origin, vehicle_index=1,
               loss=LossConfig(per=0.3), drop_at="receiver", rng=np.random.default_rng(7))
    link.send(own_state, now)                 # J2735 BSM (and compat JSON if enabled)
    for r in link.poll(now):                  # every datagram waiting, decoded
        if r.abort: ...                       # convoy-wide abort
        elif r.state is not None: member.receive(r.state, now)
    link.counters                             # sent, received, malformed, filtered, lost, ...
    link.metadata                             # for the run's metadata (drop_at, loss, ...)

The pure parts, ``Sender`` (state -> datagrams) and ``Receiver`` (datagram -> ``Received``),
do no I/O and take time as an argument; ``V2V`` adds the sockets (``multicast``).

Receiving dispatches on content: a UPER MessageFrame starts ``00 14``, a compatibility
message (``legacy_json``) starts ``{``. Both give the same ``Received``. Every datagram handled
is counted exactly once:

    datagrams == received + malformed + filtered + echoes + duplicates + rejected + lost_rx

where ``lost_rx`` is ``lost`` when losses are emulated at the receiver (the default). With
``drop_at="sender"`` the loss model decides per outgoing message instead (as the original
OpenConvoy implementation did), and ``lost`` counts messages never transmitted.

Network input never raises: anything that is not a valid message is counted as
``malformed`` and dropped with a debug log line.

Authentication (``security.auth``): with an ``Authenticator`` every BSM and abort goes out as a
signed IEEE 1609.2 SPDU (``security.spdu``, starting ``03 81``) and only verified ones are
delivered; the rest are ``rejected``, by reason in ``Authenticator.counters``
(unsigned, unknown signer, bad signature, stale, duplicate, ...). Without one, signed
SPDUs from others are still understood (their payload is used unverified).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.loss import LossConfig, LossModel, NoLoss
from openconvoy.comms.mapping import (
    DEFAULT_TIME_TOLERANCE_S,
    core_to_state,
    reconstruct_send_time,
    state_to_core,
)
from openconvoy.comms.multicast import (
    DEFAULT_GROUP,
    DEFAULT_HOP_LIMIT,
    DEFAULT_PORT,
    V2V_RCVBUF_BYTES,
    Ipv4Multicast,
    Ipv6Multicast,
    Transport,
)
from openconvoy.comms.plans import (
    PLAN_MAGIC,
    PlanDecodeError,
    decode_plan,
    encode_plan,
    peek_plan_id,
)
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator, vehicle_of
from openconvoy.comms.security.certs import PSID_ABORT, PSID_BSM, PSID_PLAN
from openconvoy.comms.tempids import TempIds
from openconvoy.core.errors import ConfigError, LinkError
from openconvoy.core.plans import Plan
from openconvoy.core.state import VehicleState

log = logging.getLogger(__name__)

DropAt = Literal["receiver", "sender"]
Source = Literal["j2735", "compat"]

#: Datagrams read from one socket between checks of the poll's time budget.
POLL_CHUNK = 32

#: A compat message from a vehicle heard over J2735 within this many seconds is a
#: duplicate (our own vehicles send both when compat is on); J2735 wins.
DUPLICATE_WINDOW_S = 1.0
#: A BSM with heading "unavailable" takes the direction of its sender's travel over at
#: least this distance (m; GPS noise makes shorter displacements meaningless).
TRAIL_HEADING_M = 0.5


@dataclass(frozen=True)
class LinkConfig:
    """Where the V2V link talks.

    Attributes:
        iface: network interface name for both families.
        group, port, hop_limit: the IPv6 multicast group for J2735 BSMs.
        compat: also send and receive the original implementation's JSON on IPv4.
        compat_group, compat_port, compat_ttl: its IPv4 group (224.0.0.1:5004, TTL 1).
        time_tolerance_s: slack for sender clocks ahead of ours when rebuilding BSM times.
    """

    iface: str
    group: str = DEFAULT_GROUP
    port: int = DEFAULT_PORT
    hop_limit: int = DEFAULT_HOP_LIMIT
    compat: bool = False
    compat_group: str = cj.COMPAT_GROUP
    compat_port: int = cj.COMPAT_PORT
    compat_ttl: int = cj.COMPAT_TTL
    time_tolerance_s: float = DEFAULT_TIME_TOLERANCE_S

    @classmethod
    def from_v2v(cls, v2v: Any, iface: str) -> LinkConfig:
        """From a convoy config's ``[v2v]`` table object (``group``, ``port``,
        ``hop_limit``, ``legacy_json`` attributes, e.g. ``openconvoy.convoy.V2VConfig``)."""
        return cls(
            iface=iface,
            group=v2v.group,
            port=v2v.port,
            hop_limit=v2v.hop_limit,
            compat=v2v.compat,
        )


@dataclass
class Counters:
    """Message counters of one V2V link (see the module docstring for the identity).

    Attributes:
        sent: messages transmitted (a J2735 BSM and its compat twin count once).
        received: messages delivered by ``poll`` (aborts included).
        malformed: datagrams that were not a valid message, or a member's BSM lacking
            position, speed, heading or time ("unavailable").
        filtered: messages from outside the convoy (unknown temporary ID or car). A J2735
            frame is recognised by the id read from its first bits (``bsm.peek_temp_id``)
            and dropped without a full decode, so a flood of foreign BSMs costs little.
        lost: messages dropped by the emulated loss model (at receiver or sender).
        echoes: our own messages heard back (multicast loop).
        duplicates: compat twins of messages already heard over J2735.
        rejected: messages authentication rejected (reasons: ``Authenticator.counters``).
        aborts: abort messages among ``received``.
        aborts_rejected: aborts among ``rejected`` (unsigned or not the convoy's).
        datagrams: datagrams handled by the receiver.
        send_errors: sends the OS refused (the link keeps going).
        recv_errors: socket receive errors (the link keeps going).
        budget_hits: polls that ended on their time budget with datagrams possibly still
            waiting (they are read by the next poll; the kernel drops what overflows).
        plans: plan messages among ``received`` (``comms.plans``).
    """

    sent: int = 0
    received: int = 0
    malformed: int = 0
    filtered: int = 0
    lost: int = 0
    echoes: int = 0
    duplicates: int = 0
    rejected: int = 0
    aborts: int = 0
    aborts_rejected: int = 0
    datagrams: int = 0
    send_errors: int = 0
    recv_errors: int = 0
    budget_hits: int = 0
    plans: int = 0


@dataclass(frozen=True, slots=True)
class Received:
    """One message delivered by the link.

    Attributes:
        state: the sender's state in the convoy's ENU frame; ``vehicle_id`` is the convoy
            index, ``t`` the sender's time (rebuilt from secMark for J2735, never after
            ``t_rx``). None for an abort that carries no position (an operator's) and for
            a plan message.
        t_rx: our receive time (the ``now`` given to ``poll``), seconds.
        abort: the convoy-wide abort flag.
        source: ``"j2735"`` or ``"compat"``.
        sender: convoy index of the sender (-1: an operator).
        temp_id: J2735 temporary ID (None for compat messages).
        msg_cnt: J2735 msgCnt (None for compat messages).
        plan: the sender's plan (``comms.plans``), for a plan message.
    """

    state: VehicleState | None
    t_rx: float
    abort: bool
    source: Source
    sender: int
    temp_id: bytes | None = None
    msg_cnt: int | None = None
    plan: Plan | None = None

    @property
    def age(self) -> float:
        """Message age ``t_rx - t_send``, seconds (0 when no state)."""
        return 0.0 if self.state is None else self.t_rx - self.state.t


def _child_rng(rng: np.random.Generator) -> np.random.Generator:
    # Independent stream per link, reproducible from the parent's seed.
    return np.random.default_rng(int(rng.integers(0, 2**63 - 1)))


def _check_drop_at(drop_at: str) -> None:
    if drop_at not in ("receiver", "sender"):
        raise ConfigError(f"drop_at must be 'receiver' or 'sender', got {drop_at!r}")


class Sender:
    """Turns own states into datagrams: msgCnt, sender-side loss, compat twin. Pure."""

    def __init__(
        self,
        temp_ids: TempIds,
        origin: Origin,
        vehicle_index: int,
        *,
        loss: LossConfig | None = None,
        drop_at: DropAt = "receiver",
        rng: np.random.Generator | None = None,
        compat_enabled: bool = False,
        counters: Counters | None = None,
        auth: Authenticator | None = None,
    ) -> None:
        _check_drop_at(drop_at)
        if auth is not None and compat_enabled:
            raise ConfigError(
                "the compatibility JSON format cannot be signed: disable compat or auth"
            )
        self.auth = auth
        self.temp_id = temp_ids.id_of(vehicle_index)
        self.origin = origin
        self.vehicle_index = vehicle_index
        self.compat_enabled = compat_enabled
        self.counters = counters if counters is not None else Counters()
        self.msg_cnt = 0
        self._loss: LossModel = NoLoss()
        if loss is not None and drop_at == "sender":
            self._loss = loss.make()
            self._loss.reset(_child_rng(rng if rng is not None else np.random.default_rng(0)))

    def datagrams(self, state: VehicleState, now: float) -> tuple[bytes, bytes | None] | None:
        """(BSM frame, compat JSON or None) for ``state`` at ``now``; None if the emulated
        sender-side loss drops it (counted in ``lost``). msgCnt advances either way, so
        receivers see the gap."""
        if state.vehicle_id != self.vehicle_index:
            raise ConfigError(
                f"state of vehicle {state.vehicle_id} sent by vehicle {self.vehicle_index}"
            )
        core = state_to_core(state, self.origin, self.temp_id, self.msg_cnt)
        self.msg_cnt = (self.msg_cnt + 1) % (j.MSG_CNT_MAX + 1)
        if self._loss.lost(now):
            self.counters.lost += 1
            return None
        frame = j.encode_frame(core, check=False)  # the mapping clamps every field
        if self.auth is not None:
            frame = self.auth.sign(frame, PSID_BSM, now)
        twin = cj.encode_state(state, self.origin) if self.compat_enabled else None
        return frame, twin


class Receiver:
    """Turns datagrams into ``Received`` messages, counting every one. Pure.

    ``handle`` never raises on any input bytes.
    """

    def __init__(
        self,
        temp_ids: TempIds,
        origin: Origin,
        vehicle_index: int,
        *,
        loss: LossConfig | None = None,
        drop_at: DropAt = "receiver",
        rng: np.random.Generator | None = None,
        time_tolerance_s: float = DEFAULT_TIME_TOLERANCE_S,
        counters: Counters | None = None,
        auth: Authenticator | None = None,
    ) -> None:
        _check_drop_at(drop_at)
        self.auth = auth
        self.temp_ids = temp_ids
        self.origin = origin
        self.vehicle_index = vehicle_index
        self.own_id = temp_ids.id_of(vehicle_index)
        self.time_tolerance_s = time_tolerance_s
        self.counters = counters if counters is not None else Counters()
        # One loss model per incoming link (sender), like the simulator's channel.
        rng = rng if rng is not None else np.random.default_rng(0)
        self._loss: dict[int, LossModel] = {}
        if loss is not None and drop_at == "receiver":
            for index, _ in temp_ids:
                model = loss.make()
                model.reset(_child_rng(rng))
                self._loss[index] = model
        self._last_j2735: dict[int, float] = {}
        # The convoy's ids (ours included, for echoes) as ``bsm.peek_temp_id`` reads them.
        self._known_ids = {int.from_bytes(t, "big") for _, t in temp_ids}
        self._heading: dict[int, float] = {}  # last heading per sender (ENU rad)
        self._anchor: dict[int, tuple[float, float]] = {}  # a trail point per sender

    def handle(self, data: bytes, t_rx: float, source: str = "") -> Received | None:
        """Classify and decode one datagram received at ``t_rx``; None if not delivered."""
        self.counters.datagrams += 1
        try:
            if data[:2] == sp.SIGNED_PREFIX:
                return self._handle_signed(data, t_rx, source)
            if self.auth is not None:
                self._unsigned(data, source)
                return None
            if data[:2] == j.BSM_FRAME_PREFIX:
                if self._foreign(data):
                    return None
                return self._handle_j2735(data, t_rx, source)
            if data[:4] == PLAN_MAGIC:
                return self._handle_plan(data, t_rx, source)
            if data.lstrip()[:1] == b"{":
                return self._handle_compat(data, t_rx, source)
            self._malformed(source, "neither a J2735 MessageFrame nor JSON")
            return None
        except Exception as exc:  # defensive: no network input may escape as an exception
            self._malformed(source, f"unexpected {type(exc).__name__}: {exc}")
            return None

    def _foreign(self, frame: bytes) -> bool:
        """A BSM frame whose id (read without decoding) is not the convoy's: counted as
        ``filtered``; a full decode (~50 us) is not worth it."""
        peeked = j.peek_temp_id(frame)
        if peeked is not None and peeked not in self._known_ids:
            self.counters.filtered += 1
            return True
        return False

    def _malformed(self, source: str, why: str) -> None:
        self.counters.malformed += 1
        log.debug("dropped malformed datagram from %s: %s", source or "?", why)
        return None

    def _rejected(self, source: str, reason: str, abort: bool = False) -> None:
        self.counters.rejected += 1
        if abort:
            self.counters.aborts_rejected += 1
        log.debug("rejected a message from %s: %s", source or "?", reason)
        return None

    def _unsigned(self, data: bytes, source: str) -> None:
        plan = data[:4] == PLAN_MAGIC
        if data[:2] != j.BSM_FRAME_PREFIX and data.lstrip()[:1] != b"{" and not plan:
            self._malformed(source, "neither a signed SPDU, a J2735 MessageFrame nor JSON")
            return None
        abort = False
        if data.lstrip()[:1] == b"{":
            try:
                abort = cj.decode(data).abort
            except cj.CompatDecodeError:
                self._malformed(source, "invalid compatibility message")
                return None
        assert self.auth is not None  # handle() calls this only when verifying
        self.auth.reject("unsigned")
        self._rejected(source, "unsigned", abort)
        return None

    def _handle_signed(self, data: bytes, t_rx: float, source: str) -> Received | None:
        try:
            spdu = sp.decode_signed(data)
        except sp.SpduDecodeError as exc:
            self._malformed(source, str(exc))
            return None
        auth = self.auth
        abort = spdu.psid == PSID_ABORT
        plan = spdu.psid == PSID_PLAN
        if plan and self._foreign_plan(spdu.payload):
            return None
        if not abort and not plan and self._foreign(spdu.payload):
            return None  # before verifying: a flood of foreign signed BSMs stays cheap
        if auth is None:  # not verifying: the payload as if it came unsigned
            signed = None
        elif spdu.digest == auth.own_digest:
            self.counters.echoes += 1
            return None
        else:
            cert = auth.check(spdu, t_rx)
            if isinstance(cert, str):
                self._rejected(source, cert, abort)
                return None
            signed = (spdu, cert)
        if abort:
            return self._handle_signed_abort(spdu, signed, t_rx, source)
        if plan:
            return self._handle_plan(spdu.payload, t_rx, source, signed)
        if spdu.psid != PSID_BSM or spdu.payload[:2] != j.BSM_FRAME_PREFIX:
            self._malformed(source, f"signed PSID {spdu.psid:#x} payload is not a BSM")
            return None
        return self._handle_j2735(spdu.payload, t_rx, source, signed)

    def _handle_signed_abort(
        self, spdu: Any, signed: Any, t_rx: float, source: str
    ) -> Received | None:
        try:
            msg = cj.decode(spdu.payload)
        except cj.CompatDecodeError as exc:
            self._malformed(source, f"signed abort: {exc}")
            return None
        if not msg.abort:
            self._malformed(source, "signed abort without the abort flag")
            return None
        sender = msg.car
        if signed is not None:
            assert self.auth is not None  # signed is only set when verifying
            vehicle = vehicle_of(signed[1])
            sender = -1 if vehicle is None else vehicle
            if self.auth.admit(spdu, t_rx) is not None:
                self._rejected(source, "replayed abort", abort=True)
                return None
        self.counters.received += 1
        self.counters.aborts += 1
        return Received(None, t_rx, True, "j2735", sender)

    def _foreign_plan(self, data: bytes) -> bool:
        """A plan message from outside the convoy (its id read without decoding)."""
        peeked = peek_plan_id(data)
        if peeked is not None and self.temp_ids.index_of(peeked) is None:
            self.counters.filtered += 1
            return True
        return False

    def _handle_plan(
        self, data: bytes, t_rx: float, source: str, signed: Any = None
    ) -> Received | None:
        """A plan message (``comms.plans``): the same checks as a BSM's — echo, convoy
        member, signer speaks for itself, no replay, emulated loss."""
        temp_id = peek_plan_id(data)
        if temp_id is None:
            self._malformed(source, "plan message too short")
            return None
        if temp_id == self.own_id:
            self.counters.echoes += 1
            return None
        sender = self.temp_ids.index_of(temp_id)
        if sender is None:
            self.counters.filtered += 1
            return None
        try:
            _, plan = decode_plan(data, sender)
        except PlanDecodeError as exc:
            self._malformed(source, str(exc))
            return None
        if signed is not None:
            assert self.auth is not None  # signed is only set when verifying
            spdu, cert = signed
            if vehicle_of(cert) != sender:
                self.auth.reject("wrong_sender")
                self._rejected(source, f"{cert.name} signed vehicle {sender}'s plan")
                return None
            if self.auth.admit(spdu, t_rx) is not None:
                self._rejected(source, f"vehicle {sender}'s plan replayed")
                return None
        if self._lost(sender, t_rx):
            return None
        self.counters.received += 1
        self.counters.plans += 1
        return Received(None, t_rx, False, "j2735", sender, temp_id, plan=plan)

    def _lost(self, sender: int, t_rx: float) -> bool:
        model = self._loss.get(sender)
        if model is not None and model.lost(t_rx):
            self.counters.lost += 1
            return True
        return False

    def _handle_j2735(
        self, data: bytes, t_rx: float, source: str, signed: Any = None
    ) -> Received | None:
        try:
            msg = j.decode_frame(data)
        except j.BsmDecodeError as exc:
            self._malformed(source, str(exc))
            return None
        core = msg.core
        if core.temp_id == self.own_id:
            self.counters.echoes += 1
            return None
        sender = self.temp_ids.index_of(core.temp_id)
        if sender is None:
            self.counters.filtered += 1
            return None
        if signed is not None:
            assert self.auth is not None  # signed is only set when verifying
            spdu, cert = signed
            if vehicle_of(cert) != sender:  # a member may only speak for itself
                self.auth.reject("wrong_sender")
                self._rejected(source, f"{cert.name} signed vehicle {sender}'s BSM")
                return None
            if self.auth.admit(spdu, t_rx, core.msg_cnt) is not None:
                self._rejected(source, f"vehicle {sender}'s BSM replayed")
                return None
        # A member's BSM without position, speed or time is no use to the convoy (NaN
        # would reach the controllers, an unknown age would look fresh forever): treated
        # as not received, so the staleness ladder sees the gap. An unavailable heading
        # (other stacks send it when stopped or slow) is filled in below.
        missing = [
            name
            for name, absent in (
                ("position", core.lat == j.LAT_UNAVAILABLE or core.lon == j.LON_UNAVAILABLE),
                ("speed", core.speed == j.SPEED_UNAVAILABLE),
                ("time", core.sec_mark >= 61000),
            )
            if absent
        ]
        if missing:
            self._malformed(source, f"BSM of vehicle {sender} lacks {', '.join(missing)}")
            return None
        # Heard over J2735 (before emulated loss: the radio did deliver it), so this
        # vehicle's compat twins are duplicates, whatever the loss model decides here.
        self._last_j2735[sender] = t_rx
        if self._lost(sender, t_rx):
            return None
        t_send = reconstruct_send_time(core.sec_mark, t_rx, self.time_tolerance_s)
        state = core_to_state(core, self.origin, sender, t_send)
        if core.heading == j.HEADING_UNAVAILABLE:
            heading = self._known_heading(sender, state)
            if heading is None:
                self._malformed(source, f"BSM of vehicle {sender} lacks heading (none known yet)")
                return None
            state = replace(state, heading=heading)
        self._remember_heading(sender, state)
        self.counters.received += 1
        return Received(state, t_rx, False, "j2735", sender, core.temp_id, core.msg_cnt)

    def _known_heading(self, sender: int, state: VehicleState) -> float | None:
        """For a BSM whose heading is unavailable: the direction of the sender's trail
        (its travel since a position at least ``TRAIL_HEADING_M`` back), else the last
        heading it sent, else None."""
        anchor = self._anchor.get(sender)
        if anchor is not None:
            dx, dy = state.x - anchor[0], state.y - anchor[1]
            if dx * dx + dy * dy >= TRAIL_HEADING_M**2:
                return math.atan2(dy, dx)
        return self._heading.get(sender)

    def _remember_heading(self, sender: int, state: VehicleState) -> None:
        self._heading[sender] = state.heading
        anchor = self._anchor.get(sender)
        if (
            anchor is None
            or (state.x - anchor[0]) ** 2 + (state.y - anchor[1]) ** 2 >= TRAIL_HEADING_M**2
        ):
            self._anchor[sender] = (state.x, state.y)

    def _handle_compat(self, data: bytes, t_rx: float, source: str) -> Received | None:
        try:
            msg = cj.decode(data)
        except cj.CompatDecodeError as exc:
            self._malformed(source, str(exc))
            return None
        if msg.car == self.vehicle_index:
            self.counters.echoes += 1
            return None
        if msg.abort:
            # Aborts are exempt from emulated loss and from the convoy filter: anyone on
            # the group (the operator's `openconvoy abort`, car -1) may stop the convoy.
            state = None
            if msg.lat_deg is not None and msg.car in self.temp_ids:
                state = self._compat_state(msg, t_rx)
            self.counters.received += 1
            self.counters.aborts += 1
            return Received(state, t_rx, True, "compat", msg.car)
        if msg.car not in self.temp_ids:
            self.counters.filtered += 1
            return None
        last = self._last_j2735.get(msg.car)
        if last is not None and t_rx - last <= DUPLICATE_WINDOW_S:
            self.counters.duplicates += 1
            return None
        if self._lost(msg.car, t_rx):
            return None
        self.counters.received += 1
        return Received(self._compat_state(msg, t_rx), t_rx, False, "compat", msg.car)

    def _compat_state(self, msg: cj.CompatMessage, t_rx: float) -> VehicleState:
        state = cj.to_state(msg, self.origin)
        if not state.t <= t_rx:  # clock ahead (or NaN): age 0, never negative
            state = replace(state, t=t_rx)
        return state


def _open_transports(
    config: LinkConfig, transport: Transport | None, compat_transport: Transport | None
) -> tuple[Transport, Transport | None]:
    """The IPv6 multicast socket and, with ``config.compat``, the IPv4 one (each unless
    injected); nothing stays open when the second cannot be opened."""
    tx = (
        transport
        if transport is not None
        else Ipv6Multicast(
            config.iface,
            config.group,
            config.port,
            config.hop_limit,
            rcvbuf_bytes=V2V_RCVBUF_BYTES,
        )
    )
    if compat_transport is not None or not config.compat:
        return tx, compat_transport
    try:
        tx4 = Ipv4Multicast(
            config.iface,
            config.compat_group,
            config.compat_port,
            config.compat_ttl,
            rcvbuf_bytes=V2V_RCVBUF_BYTES,
        )
    except (OSError, LinkError):
        tx.close()
        raise
    return tx, tx4


class V2V:
    """A vehicle's V2V link: J2735 BSMs over IPv6 multicast (+ compat JSON over IPv4).

    Args:
        config: interface, groups, ports (``LinkConfig``).
        temp_ids: the convoy's temporary IDs (index 0 = leader).
        origin: the convoy's ENU origin.
        vehicle_index: this vehicle's convoy index.
        loss: emulated loss (``LossConfig``); its latency is not emulated on vehicles
            (the real network has its own). None: no emulated loss.
        drop_at: ``"receiver"`` (default: each incoming link has its own loss model) or
            ``"sender"`` (one draw per outgoing message, as the original implementation).
        rng: random source for the loss models (seeded: the same seed, the same drops).
        transport, compat_transport: injected sockets (tests); by default opened on
            ``config.iface`` (the IPv4 one only when ``config.compat``).
        clock: monotonic clock (s) that times ``poll``'s budget.
        auth: sign what is sent and deliver only verified messages (``comms.security.auth``);
            None: unsigned (``[v2v] auth = "off"``).
    """

    def __init__(
        self,
        config: LinkConfig,
        temp_ids: TempIds,
        origin: Origin,
        vehicle_index: int,
        *,
        loss: LossConfig | None = None,
        drop_at: DropAt = "receiver",
        rng: np.random.Generator | None = None,
        transport: Transport | None = None,
        compat_transport: Transport | None = None,
        auth: Authenticator | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        _check_drop_at(drop_at)
        self._clock = clock
        if auth is not None and config.compat:
            raise ConfigError(
                "the compatibility JSON format cannot be signed: disable compat or auth"
            )
        self.auth = auth
        self.config = config
        self.vehicle_index = vehicle_index
        self.loss = loss
        self.drop_at = drop_at
        self.counters = Counters()
        rng = rng if rng is not None else np.random.default_rng(0)
        self.sender = Sender(
            temp_ids,
            origin,
            vehicle_index,
            loss=loss,
            drop_at=drop_at,
            rng=_child_rng(rng),
            compat_enabled=config.compat,
            counters=self.counters,
            auth=auth,
        )
        self.receiver = Receiver(
            temp_ids,
            origin,
            vehicle_index,
            loss=loss,
            drop_at=drop_at,
            rng=_child_rng(rng),
            time_tolerance_s=config.time_tolerance_s,
            counters=self.counters,
            auth=auth,
        )
        self._tx, self._tx4 = _open_transports(config, transport, compat_transport)
        self._warned_send = False
        # Compile the ASN.1 spec now, not on the first message (it takes ~0.2 s).
        j.warm_up()

    @property
    def metadata(self) -> dict[str, Any]:
        """What to record in the run's metadata about this link."""
        return {
            "iface": self.config.iface,
            "group": self.config.group,
            "port": self.config.port,
            "hop_limit": self.config.hop_limit,
            "compat": self.config.compat,
            "vehicle_index": self.vehicle_index,
            "temp_id": self.sender.temp_id.hex(),
            "drop_at": self.drop_at,
            "loss": asdict(self.loss) if self.loss is not None else None,
            "latency_emulated": False,
            "auth": self._auth_metadata(),
        }

    def _auth_metadata(self) -> dict[str, Any] | None:
        a = self.auth
        if a is None:
            return None
        own = a.credentials.certificate
        return {
            "certificate": None if own is None else own.name,
            "window_s": a.guard.window_s,
            "rejected": dict(a.counters.rejected),
            "certificates_learned": a.counters.certificates_learned,
            "certificates_sent": a.counters.certificates_sent,
            "requests_sent": a.counters.requests_sent,
        }

    def _send(self, transport: Transport, data: bytes) -> bool:
        try:
            transport.send(data)
            return True
        except OSError as exc:
            # A vehicle must keep driving (and its failsafes keep working) when the radio
            # hiccups; the counters and staleness ladder show the consequences.
            self.counters.send_errors += 1
            level = logging.DEBUG if self._warned_send else logging.WARNING
            self._warned_send = True
            log.log(level, "V2V send failed: %s", exc)
            return False

    def send(self, state: VehicleState, now: float) -> bool:
        """Broadcast own ``state`` (``vehicle_id`` must be ours) at ``now``, seconds.

        Returns True if transmitted (False: dropped by emulated sender-side loss, or the
        OS refused it).
        """
        out = self.sender.datagrams(state, now)
        if out is None:
            return False
        frame, twin = out
        ok = self._send(self._tx, frame)
        if twin is not None and self._tx4 is not None:
            ok = self._send(self._tx4, twin) or ok
        if ok:
            self.counters.sent += 1
        return ok

    def send_plan(self, plan: Plan, now: float) -> bool:
        """Broadcast own ``plan`` (``comms.plans``; signed under ``PSID_PLAN`` with auth) at
        ``now`` (s), beside the BSM τ just sent. True if transmitted."""
        if plan.vehicle_id != self.vehicle_index:
            raise ConfigError(
                f"plan of vehicle {plan.vehicle_id} sent by vehicle {self.vehicle_index}"
            )
        data = encode_plan(plan, self.sender.temp_id)
        if self.auth is not None:
            data = self.auth.sign(data, PSID_PLAN, now)
        return self._send(self._tx, data)

    def send_abort(self, now: float, state: VehicleState | None = None) -> None:
        """Broadcast a convoy-wide abort from this vehicle (with its ``state`` if given)."""
        if state is not None:
            data = cj.encode_state(state, self.sender.origin, abort=True)
        else:
            data = cj.make_abort(now, car=self.vehicle_index)
        if self.auth is not None:
            data = self.auth.sign(data, PSID_ABORT, now)
        self._send(self._tx, data)
        if self._tx4 is not None:
            self._send(self._tx4, data)

    def poll(self, now: float, budget_s: float | None = None) -> list[Received]:
        """Messages waiting, decoded and filtered, received at ``now`` (seconds).

        With ``budget_s`` the poll reads for at most that long (monotonic clock) and leaves
        the rest in the socket buffers for the next poll, so a flood of datagrams cannot
        stall the caller's control loop; the sockets take turns in chunks of
        ``POLL_CHUNK``. None: every datagram waiting.
        """
        out: list[Received] = []
        transports = [self._tx] if self._tx4 is None else [self._tx, self._tx4]
        deadline = math.inf if budget_s is None else self._clock() + budget_s
        while transports:
            for transport in list(transports):
                try:
                    dgrams = transport.recv_all(POLL_CHUNK)
                except OSError as exc:  # e.g. the interface went down: keep the vehicle going
                    self.counters.recv_errors += 1
                    log.debug("V2V receive failed: %s", exc)
                    dgrams = []
                if len(dgrams) < POLL_CHUNK:
                    transports.remove(transport)  # drained
                for dgram in dgrams:
                    r = self.receiver.handle(dgram.data, now, dgram.source)
                    if r is not None:
                        out.append(r)
            if transports and self._clock() >= deadline:
                self.counters.budget_hits += 1
                break
        return out

    def close(self) -> None:
        """Close the sockets."""
        self._tx.close()
        if self._tx4 is not None:
            self._tx4.close()

    def __enter__(self) -> V2V:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def send_abort(
    iface: str,
    *,
    group: str = DEFAULT_GROUP,
    port: int = DEFAULT_PORT,
    hop_limit: int = DEFAULT_HOP_LIMIT,
    compat_enabled: bool = False,
    compat_group: str = cj.COMPAT_GROUP,
    compat_port: int = cj.COMPAT_PORT,
    now: float | None = None,
    repeat: int = 3,
    interval_s: float = 0.05,
    auth: Authenticator | None = None,
) -> int:
    """Send a convoy-wide abort as an operator (``event_flags.car = -1``).

    The compatibility-format JSON with ``abort: true`` goes to the IPv6 BSM group (our
    vehicles) and, with ``compat_enabled``, to the IPv4 group (vehicles running the
    original implementation). Sent ``repeat`` times ``interval_s`` apart, since multicast
    has no acknowledgement. ``now`` (seconds, default the system clock) stamps the message.
    With ``security.auth`` the abort is a signed SPDU (PSID ``PSID_ABORT``; each repeat has its own
    generation time), and only on the IPv6 group. Returns the number of datagrams sent.
    """
    if repeat < 1:
        raise ConfigError(f"repeat must be at least 1, got {repeat}")
    if auth is not None and compat_enabled:
        raise ConfigError("a signed abort cannot go out in the compatibility JSON format")
    t0 = time.time() if now is None else now
    socks: list[Transport] = [Ipv6Multicast(iface, group, port, hop_limit)]
    try:
        if compat_enabled:
            socks.append(Ipv4Multicast(iface, compat_group, compat_port))
        n = 0
        for i in range(repeat):
            if i:
                time.sleep(interval_s)
            data = cj.make_abort(t0)
            if auth is not None:
                data = auth.sign(data, PSID_ABORT, t0 if now is not None else time.time())
            for s in socks:
                try:
                    s.send(data)
                except OSError as exc:  # the one command that must fail clearly
                    raise LinkError(f"abort not sent on {iface}: {exc.strerror or exc}") from None
                n += 1
        return n
    finally:
        for s in socks:
            s.close()


__all__ = [
    "Counters",
    "LinkConfig",
    "Received",
    "Receiver",
    "Sender",
    "V2V",
    "send_abort",
    "DUPLICATE_WINDOW_S",
    "POLL_CHUNK",
]
