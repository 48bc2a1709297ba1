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
do no I/O and take time as an argument; ``V2V`` adds the sockets (``multicast``), or with
``LinkConfig(transport="ros2")`` a ROS 2 topic over DDS (``dds``): the same bytes, and the
same decoding, verification, counting and dropping.

Receiving dispatches on content: a UPER MessageFrame starts ``00 14``, a compatibility
message (``legacy_json``) starts ``{``. Both give the same ``Received``. Every datagram handled
is counted exactly once:

    datagrams == received + malformed + filtered + echoes + duplicates + rejected + lost_rx
                 + shed + replays

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

import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import numpy as np

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.guards import Alerts, FrameMemory, JumpCheck, SkewMeter, sec_mark_offset
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
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator, vehicle_of
from openconvoy.comms.security.certs import (
    PSID_ABORT,
    PSID_BSM,
    PSID_COMPLETE,
    PSID_PLAN,
    Certificate,
)
from openconvoy.comms.tempids import TempIds
from openconvoy.core.errors import ConfigError, LinkError
from openconvoy.core.plans import Plan
from openconvoy.core.state import VehicleState

log = logging.getLogger(__name__)

DropAt = Literal["receiver", "sender"]
Source = Literal["j2735", "compat"]

#: Datagrams read from one socket between checks of the poll's time budget.
POLL_CHUNK = 32
#: Share of a poll's budget spent reading datagrams; the rest verifies signatures.
READ_SHARE = 0.8

#: A compat message from a vehicle heard over J2735 within this many seconds is a
#: duplicate (our own vehicles send both when compat is on); J2735 wins.
DUPLICATE_WINDOW_S = 1.0
#: A BSM with heading "unavailable" takes the direction of its sender's travel over at
#: least this distance (m; GPS noise makes shorter displacements meaningless).
TRAIL_HEADING_M = 0.5


#: Signed SPDUs verified per claimed sender (and per abort / completion group) per poll:
#: a member sends one message per tick, so a flood claiming it costs a few verifications.
VERIFY_PER_SENDER = 4
#: Wrongly signed messages a second, claiming one sender, that make a flood (said once).
FLOOD_ALERT_PER_S = 20
#: A member's clock offset over half the tolerance is said at most this often (s).
SKEW_ALERT_PERIOD_S = 60.0
#: Payload of the leader's "scenario complete" (JSON, signed with PSID_COMPLETE).
COMPLETE_PREFIX = b'{"openconvoy":"complete"'
_KINDS = {PSID_ABORT: "abort", PSID_COMPLETE: "complete", PSID_PLAN: "plan"}
_GROUPS = {"abort": -2, "complete": -3}


def make_complete(t: float, car: int = 0) -> bytes:
    """The payload of a "scenario complete" message from vehicle ``car`` at time ``t`` (s)."""
    body = {"openconvoy": "complete", "car": car, "t": round(t, 6)}
    return json.dumps(body, separators=(",", ":")).encode()


def parse_complete(payload: bytes) -> int | None:
    """The sender of a "scenario complete" payload, None if it is not one."""
    if not payload.startswith(COMPLETE_PREFIX) or len(payload) > 256:
        return None
    try:
        body = json.loads(payload)
    except ValueError:
        return None
    car = body.get("car") if isinstance(body, dict) else None
    return car if isinstance(car, int) and not isinstance(car, bool) else None


@dataclass(frozen=True, slots=True)
class _Pending:
    """A signed SPDU waiting for its signature to be verified."""

    group: int  # the claimed sender's convoy index; -1 none, -2 aborts, -3 completions
    source: str
    spdu: sp.SignedSpdu
    kind: str


def schedule(
    pending: Sequence[_Pending], trusted: dict[int, str], per_sender: int = VERIFY_PER_SENDER
) -> tuple[list[_Pending], list[_Pending]]:
    """(to verify, in order; shed) for SPDUs awaiting verification (D52).

    Per group (claimed sender): from the source its last verified message came from
    first, then those carrying a certificate (it introduces the digests of the others),
    then newest generation time first, at most ``per_sender``; the groups take
    turns, so a flood claiming one sender delays nobody else, and the sender it claims
    keeps getting its own newest messages verified as long as they come from where they
    used to."""
    groups: dict[int, list[_Pending]] = {}
    for p in pending:
        groups.setdefault(p.group, []).append(p)
    queues: list[list[_Pending]] = []
    shed: list[_Pending] = []
    for g, items in groups.items():
        home = trusted.get(g)
        # a certificate before the digests it introduces
        items.sort(
            key=lambda p: (p.source != home, p.spdu.certificate is None, -p.spdu.generation_time)
        )
        queues.append(items[:per_sender])
        shed.extend(items[per_sender:])
    order: list[_Pending] = []
    for k in range(per_sender):
        order.extend(q[k] for q in queues if k < len(q))
    return order, shed


TRANSPORTS = ("multicast", "ros2")
"""What carries the V2V bytes (``LinkConfig.transport``)."""


@dataclass(frozen=True)
class LinkConfig:
    """Where the V2V link talks.

    Attributes:
        iface: network interface name for both families.
        group, port, hop_limit: the IPv6 multicast group for J2735 BSMs.
        compat: also send and receive the original implementation's JSON on IPv4.
        compat_group, compat_port, compat_ttl: its IPv4 group (224.0.0.1:5004, TTL 1).
        time_tolerance_s: slack for sender clocks ahead of ours when rebuilding BSM times.
        transport: ``"multicast"`` (the default: IPv6 multicast on ``iface``) or ``"ros2"``
            (the same bytes on ROS 2 topic ``ros2_topic`` of DDS domain ``ros2_domain``,
            Cyclone DDS kept on ``iface``: ``comms.dds``).
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
    transport: str = "multicast"
    ros2_topic: str = "/openconvoy/v2v"
    ros2_domain: int = 0

    def __post_init__(self) -> None:
        if self.transport not in TRANSPORTS:
            raise ConfigError(
                f"V2V transport {self.transport!r} is not one of {', '.join(TRANSPORTS)}"
            )
        if self.transport == "ros2":
            from openconvoy.comms.dds import dds_topic

            dds_topic(self.ros2_topic)  # ConfigError naming the rule

    @classmethod
    def from_v2v(cls, v2v: Any, iface: str) -> LinkConfig:
        """From a convoy config's ``[v2v]`` table object (``group``, ``port``,
        ``hop_limit``, ``legacy_json`` attributes, e.g. ``openconvoy.convoy.V2VConfig``;
        ``transport``, ``ros2_topic``, ``ros2_domain`` when it has them)."""
        return cls(
            iface=iface,
            group=v2v.group,
            port=v2v.port,
            hop_limit=v2v.hop_limit,
            compat=v2v.compat,
            time_tolerance_s=getattr(v2v, "replay_window_s", DEFAULT_TIME_TOLERANCE_S),
            transport=getattr(v2v, "transport", "multicast"),
            ros2_topic=getattr(v2v, "ros2_topic", "/openconvoy/v2v"),
            ros2_domain=getattr(v2v, "ros2_domain", 0),
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
        shed: signed messages left unverified: beyond their sender's share of a poll
            (``VERIFY_PER_SENDER``) or its time budget (a flood; ``Receiver.handle_batch``).
        replays: unsigned frames already delivered once (verbatim replays).
        impersonations: verified BSMs carrying our own temp id, signed by someone else
            (also among ``rejected``).
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
    shed: int = 0
    replays: int = 0
    impersonations: int = 0
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
    complete: bool = False
    """The leader's "scenario complete" (``state`` None, ``sender`` 0)."""
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
        self._index_of_id = {int.from_bytes(t, "big"): i for i, t in temp_ids}
        self._heading: dict[int, float] = {}  # last heading per sender (ENU rad)
        self._anchor: dict[int, tuple[float, float]] = {}  # a trail point per sender
        self._frames = FrameMemory()  # unsigned frames delivered (replays)
        self._jumps = JumpCheck()
        self._trusted: dict[int, str] = {}  # group -> source of its last verified message
        self._bad_window: dict[int, tuple[float, int]] = {}
        self.skew = SkewMeter()
        """Each member's clock offset from ours (``guards.SkewMeter``)."""
        self.alerts = Alerts()
        """Operator lines: floods, disagreement about auth, jumps, impersonation."""
        self.last_t_rx = -math.inf
        """The latest receive time handled (s)."""
        self.auth_mismatch: dict[int, str] = {}
        """Members heard using V2V authentication differently from us (their first line)."""

    def handle(self, data: bytes, t_rx: float, source: str = "") -> Received | None:
        """Classify and decode one datagram received at ``t_rx``; None if not delivered.
        (``handle_batch`` of one.)"""
        out = self.handle_batch([(data, source)], t_rx)
        return out[0] if out else None

    def handle_batch(
        self,
        items: Sequence[tuple[bytes, str]],
        t_rx: float,
        *,
        deadline: float = math.inf,
        clock: Callable[[], float] | None = None,
    ) -> list[Received]:
        """Classify and decode datagrams ``(data, source)`` received at ``t_rx``, in order.

        Signed SPDUs that need a signature verified are verified last, scheduled so that a
        flood cannot starve anyone (``schedule``): per claimed sender (the id its payload
        claims; aborts and completions are groups of their own) at most
        ``VERIFY_PER_SENDER``, the source its last verified message came from first, then
        the newest; groups take turns. What is left when ``clock()`` passes ``deadline``
        is ``shed`` (counted, not delivered). Never raises."""
        out: list[Received] = []
        pending: list[_Pending] = []
        self.prepare_batch(items, t_rx, pending, out)
        self.verify_batch(pending, t_rx, out, deadline=deadline, clock=clock)
        return out

    def prepare_batch(
        self,
        items: Sequence[tuple[bytes, str]],
        t_rx: float,
        pending: list[_Pending],
        out: list[Received],
    ) -> None:
        """The cheap part of ``handle_batch``: what needs no signature verified goes to
        ``out`` (or is counted), signed SPDUs to verify to ``pending``."""
        self.last_t_rx = t_rx
        for data, source in items:
            self.counters.datagrams += 1
            try:
                if data[:2] == sp.SIGNED_PREFIX:
                    r = self._prepare_signed(data, t_rx, source)
                    if isinstance(r, _Pending):
                        pending.append(r)
                        continue
                else:
                    r = self._handle_plain(data, t_rx, source)
                if r is not None:
                    out.append(r)
            except Exception as exc:  # defensive: no network input may escape as an exception
                self._malformed(source, f"unexpected {type(exc).__name__}: {exc}")

    def verify_batch(
        self,
        pending: Sequence[_Pending],
        t_rx: float,
        out: list[Received],
        *,
        deadline: float = math.inf,
        clock: Callable[[], float] | None = None,
    ) -> None:
        """The rest of ``handle_batch``: verify ``pending`` as ``schedule`` orders it until
        ``deadline``, deliver into ``out`` in generation order."""
        order, shed = schedule(pending, self._trusted)
        self._note_shed(shed, t_rx)
        verified: list[tuple[_Pending, Certificate]] = []
        firsts = {id(p) for p in order[: len({p.group for p in order})]}
        for item in order:
            # Past the deadline only each group's first item is still verified when it
            # comes from that group's usual source: a genuine sender's newest message costs
            # one verification, whatever floods alongside.
            if (
                clock is not None
                and clock() >= deadline
                and not (id(item) in firsts and self._trusted.get(item.group) == item.source)
            ):
                self._note_shed([item], t_rx)
                continue
            try:
                cert = self._verify(item, t_rx)
            except Exception as exc:  # defensive, as above
                self._malformed(item.source, f"unexpected {type(exc).__name__}: {exc}")
                cert = None
            if cert is not None:
                verified.append((item, cert))
        # Verified newest first, delivered in the order they were generated (the replay
        # guard's order check sees each sender's messages as they were sent).
        verified.sort(key=lambda v: v[0].spdu.generation_time)
        for item, cert in verified:
            try:
                r = self._deliver(item.spdu, cert, item.kind, t_rx, item.source)
            except Exception as exc:  # defensive, as above
                self._malformed(item.source, f"unexpected {type(exc).__name__}: {exc}")
                r = None
            if r is not None:
                out.append(r)

    def _handle_plain(self, data: bytes, t_rx: float, source: str) -> Received | None:
        if self.auth is not None:
            self._unsigned(data, source, t_rx)
            return None
        if data[:2] == j.BSM_FRAME_PREFIX:
            if self._foreign(data):
                return None
            return self._handle_j2735(data, t_rx, source)
        if data.startswith(COMPLETE_PREFIX):
            return self._handle_complete(data, None, t_rx, source)
        if data[:4] == PLAN_MAGIC:
            return self._handle_plan(data, t_rx, source)
        if data.lstrip()[:1] == b"{":
            return self._handle_compat(data, t_rx, source)
        self._malformed(source, "neither a J2735 MessageFrame nor JSON")
        return None

    def _foreign(self, frame: bytes) -> bool:
        """A BSM frame whose id (read without decoding) is not the convoy's: counted as
        ``filtered``; a full decode (~50 us) is not worth it."""
        peeked = j.peek_temp_id(frame)
        if peeked is not None and peeked not in self._known_ids:
            self.counters.filtered += 1
            return True
        return False

    def _claimed(self, frame: bytes) -> int:
        """The convoy index a BSM frame claims (read without decoding), -1 if none."""
        peeked = j.peek_temp_id(frame)
        if peeked is None:
            return -1
        index = self._index_of_id.get(peeked)
        return -1 if index is None else index

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

    def _unsigned(self, data: bytes, source: str, t_rx: float) -> None:
        plan = data[:4] == PLAN_MAGIC
        if data[:2] != j.BSM_FRAME_PREFIX and data.lstrip()[:1] != b"{" and not plan:
            self._malformed(source, "neither a signed SPDU, a J2735 MessageFrame nor JSON")
            return None
        abort = False
        if data[:2] == j.BSM_FRAME_PREFIX:
            if self._foreign(data):
                return None  # another convoy's (or nobody's) traffic: filtered, not ours
            claimed = self._claimed(data)
            if claimed >= 0 and claimed != self.vehicle_index:
                self._mismatch(claimed, t_rx, "sends unsigned V2V messages")
        elif not plan and not data.startswith(COMPLETE_PREFIX):
            try:
                abort = cj.decode(data).abort
            except cj.CompatDecodeError:
                self._malformed(source, "invalid compatibility message")
                return None
        assert self.auth is not None  # handle() calls this only when verifying
        self.auth.reject("unsigned")
        self._rejected(source, "unsigned", abort)
        return None

    def _mismatch(self, sender: int, t_rx: float, what: str) -> None:
        """Member ``sender`` does not use V2V authentication as we do (``what`` it does)."""
        ours = "requires signatures" if self.auth is not None else 'has [v2v] auth = "off"'
        line = (
            f"vehicle {self.vehicle_index}: vehicle {sender} {what} while this vehicle {ours}: "
            "the convoy disagrees about [v2v] auth"
        )
        if sender not in self.auth_mismatch:
            self.auth_mismatch[sender] = line
        self.alerts.raise_("auth", sender, t_rx, line)

    def _prepare_signed(self, data: bytes, t_rx: float, source: str) -> Received | _Pending | None:
        """Everything about a signed SPDU short of verifying its signature: decoded,
        filtered, checked for freshness and duplicates (cheap); a ``_Pending`` to verify,
        or what to deliver without verifying (no ``auth``), or None (counted)."""
        try:
            spdu = sp.decode_signed(data)
        except sp.SpduDecodeError as exc:
            self._malformed(source, str(exc))
            return None
        kind = _KINDS.get(spdu.psid, "bsm")
        if kind == "bsm" and self._foreign(spdu.payload):
            return None  # before verifying: a flood of foreign signed BSMs stays cheap
        if kind == "plan" and self._foreign_plan(spdu.payload):
            return None  # before verifying: a flood of foreign signed BSMs stays cheap
        if kind == "bsm":
            group = self._claimed(spdu.payload)
        elif kind == "plan":  # a plan is budgeted with its sender's BSMs
            peeked = peek_plan_id(spdu.payload)
            index = None if peeked is None else self.temp_ids.index_of(peeked)
            group = -1 if index is None else index
        else:
            group = _GROUPS[kind]
        auth = self.auth
        if auth is None:  # not verifying: the payload as if it came unsigned
            if kind == "bsm" and group >= 0 and group != self.vehicle_index:
                self._mismatch(group, t_rx, "signs its V2V messages")
            return self._deliver(spdu, None, kind, t_rx, source)
        if spdu.digest == auth.own_digest:
            self.counters.echoes += 1
            return None
        reason = auth.precheck(spdu, t_rx)
        if reason is not None:
            if reason in ("stale", "future"):
                self._probe_skew(spdu, t_rx)
            self._rejected(source, reason, kind == "abort")
            return None
        return _Pending(group, source, spdu, kind)

    def _verify(self, item: _Pending, t_rx: float) -> Certificate | None:
        """Verify a scheduled SPDU: its signer's certificate, or None (counted)."""
        assert self.auth is not None  # only SPDUs to verify are scheduled
        cert = self.auth.check(item.spdu, t_rx)
        if isinstance(cert, str):
            if cert == "bad_signature":
                self._note_bad(item, t_rx)
            signer = self.auth.known(item.spdu.digest)
            if item.kind == "abort" and cert == "not_permitted" and signer is not None:
                self._abort_not_permitted(signer, t_rx)
            self._rejected(item.source, cert, item.kind == "abort")
            return None
        self._trusted[item.group] = item.source
        return cert

    def _deliver(
        self, spdu: sp.SignedSpdu, cert: Certificate | None, kind: str, t_rx: float, source: str
    ) -> Received | None:
        signed = None if cert is None else (spdu, cert)
        if cert is not None and self.auth is not None and self.auth.precheck(spdu, t_rx):
            # A copy verified in the same poll as the first one (both passed the precheck
            # before either was recorded): a duplicate now that the first is delivered.
            self._rejected(source, "duplicate", kind == "abort")
            return None
        if kind == "abort":
            return self._handle_signed_abort(spdu, signed, t_rx, source)
        if kind == "complete":
            return self._handle_complete(spdu.payload, signed, t_rx, source)
        if kind == "plan":
            return self._handle_plan(spdu.payload, t_rx, source, signed)
        if spdu.psid != PSID_BSM or spdu.payload[:2] != j.BSM_FRAME_PREFIX:
            self._malformed(source, f"signed PSID {spdu.psid:#x} payload is not a BSM")
            return None
        return self._handle_j2735(spdu.payload, t_rx, source, signed)

    def _probe_skew(self, spdu: sp.SignedSpdu, t_rx: float) -> None:
        """A stale or future SPDU from a member whose signature verifies (at most once a
        second per signer): its clock offset, to name it (``start_refusal``)."""
        assert self.auth is not None
        cert = self.auth.probe_skew(spdu, t_rx)
        sender = None if cert is None else vehicle_of(cert)
        if sender is not None and sender in self.temp_ids and sender != self.vehicle_index:
            self.skew.sample(sender, c.unix_of_time64(spdu.generation_time) - t_rx, t_rx)

    def _note_bad(self, item: _Pending, t_rx: float) -> None:
        """Count a wrongly signed SPDU towards its group's flood rate; tell the operator
        once a flood is on (``FLOOD_ALERT_PER_S``)."""
        t0, n = self._bad_window.get(item.group, (t_rx, 0))
        if t_rx - t0 > 1.0:
            t0, n = t_rx, 0
        self._bad_window[item.group] = (t0, n + 1)
        if n + 1 >= FLOOD_ALERT_PER_S:
            self._flood_alert(item.group, item.source, t_rx)

    def _note_shed(self, shed: Sequence[_Pending], t_rx: float) -> None:
        self.counters.shed += len(shed)
        for item in shed[:1]:
            self._flood_alert(item.group, item.source, t_rx)

    def _flood_alert(self, group: int, source: str, t_rx: float) -> None:
        who = (
            f"vehicle {group}"
            if group >= 0
            else {-2: "an abort", -3: "a completion"}.get(group, "no member")
        )
        self.alerts.raise_(
            "flood",
            group,
            t_rx,
            f"vehicle {self.vehicle_index}: V2V flood: wrongly signed or surplus messages "
            f"claiming {who} (from {source or '?'}); verifying that sender's newest first "
            f"(shed so far {self.counters.shed}, bad signatures "
            f"{self.auth.counters.rejected['bad_signature'] if self.auth else 0})",
        )

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
            if vehicle is not None:  # only the authority or an operator stops the convoy
                self.auth.reject("not_permitted")
                self._rejected(source, f"abort signed by {signed[1].name}", abort=True)
                self._abort_not_permitted(signed[1], t_rx)
                return None
            sender = -1
            if self.auth.admit(spdu, t_rx) is not None:
                self._rejected(source, "replayed abort", abort=True)
                return None
        self.counters.received += 1
        self.counters.aborts += 1
        return Received(None, t_rx, True, "j2735", sender)

    def _handle_complete(
        self, payload: bytes, signed: Any, t_rx: float, source: str
    ) -> Received | None:
        """The leader's "scenario complete": delivered when the leader's certificate signed
        it (or, unsigned, when this vehicle does not verify), once."""
        car = parse_complete(payload)
        if car is None:
            self._malformed(source, "invalid completion message")
            return None
        if signed is not None:
            assert self.auth is not None
            spdu, cert = signed
            if vehicle_of(cert) != 0:
                self.auth.reject("wrong_sender")
                self._rejected(source, f"completion signed by {cert.name}, not the leader")
                return None
            if self.auth.admit(spdu, t_rx) is not None:
                self._rejected(source, "replayed completion")
                return None
        elif car != 0:
            self.counters.filtered += 1
            return None
        elif self._frames.seen(payload, t_rx):
            self.counters.replays += 1
            return None
        self.counters.received += 1
        return Received(None, t_rx, False, "j2735", 0, complete=True)

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
            if signed is not None:  # verified, and not signed by us (echoes never get here)
                self._impersonation(signed[1], t_rx, source)
                return None
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
        elif self._frames.seen(data, t_rx):
            # Unsigned: the frame itself is the only evidence; a verbatim replay, even an
            # hour late when its secMark looks fresh again, is not delivered twice (D46).
            self.counters.replays += 1
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
        if signed is not None:
            # The signed generation time (µs, the full date): the age whatever the secMark
            # and the minute; a clock ahead (within the window) reads as age 0 (D50).
            t_claimed = c.unix_of_time64(signed[0].generation_time)
            t_send = min(t_claimed, t_rx)
            self.skew.sample(sender, t_claimed - t_rx, t_rx)
        else:
            t_send = reconstruct_send_time(core.sec_mark, t_rx, self.time_tolerance_s)
            self.skew.sample(sender, sec_mark_offset(core.sec_mark, t_rx), t_rx)
        state = core_to_state(core, self.origin, sender, t_send)
        jump = self._jumps.check(sender, state.t, state.x, state.y)
        if jump is not None:
            self.alerts.raise_(
                "jump",
                sender,
                t_rx,
                f"vehicle {self.vehicle_index}: vehicle {sender}'s position jumped "
                f"{jump.distance_m:.1f} m in {jump.dt_s:.2f} s: two stations sending as "
                "vehicle {sender}? (a stolen key: re-issue it with `openconvoy keys issue "
                "--force`)".replace("{sender}", str(sender)),
            )
        if core.heading == j.HEADING_UNAVAILABLE:
            heading = self._known_heading(sender, state)
            if heading is None:
                self._malformed(source, f"BSM of vehicle {sender} lacks heading (none known yet)")
                return None
            state = replace(state, heading=heading)
        self._remember_heading(sender, state)
        self.counters.received += 1
        return Received(state, t_rx, False, "j2735", sender, core.temp_id, core.msg_cnt)

    def _abort_not_permitted(self, cert: Certificate, t_rx: float) -> None:
        """Tell the operator a vehicle's key signed an abort (ignored, D63)."""
        who = vehicle_of(cert)
        self.alerts.raise_(
            "abort",
            -1 if who is None else who,
            t_rx,
            f"vehicle {self.vehicle_index}: ignored an abort signed by {cert.name} (only the "
            "convoy authority or an operator key may sign aborts)",
        )

    def _impersonation(self, cert: Certificate, t_rx: float, source: str) -> None:
        """A verified BSM carrying our own temp id, signed by someone else (D63)."""
        assert self.auth is not None
        self.counters.impersonations += 1
        self.auth.reject("wrong_sender")
        self._rejected(source, f"{cert.name} signed a BSM with our temp id")
        who = vehicle_of(cert)
        self.alerts.raise_(
            "impersonation",
            -1 if who is None else who,
            t_rx,
            f"vehicle {self.vehicle_index}: {cert.name} signs BSMs with this vehicle's "
            f"temp id (from {source or '?'})",
        )

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


def open_transport(config: LinkConfig, vehicle_index: int = 0, members: int = 3) -> Transport:
    """The J2735 transport ``config`` names: the IPv6 multicast socket, or with
    ``transport = "ros2"`` the ROS 2 topic (``comms.dds.DdsTransport``, which stamps what
    it sends with ``vehicle_index`` and keeps a queue sized for ``members`` vehicles)."""
    if config.transport == "ros2":
        from openconvoy.comms.dds import DdsTransport, depth_for

        return DdsTransport(
            config.iface,
            config.ros2_topic,
            config.ros2_domain,
            vehicle_id=vehicle_index,
            depth=depth_for(members),
        )
    return Ipv6Multicast(
        config.iface, config.group, config.port, config.hop_limit, rcvbuf_bytes=V2V_RCVBUF_BYTES
    )


def _open_transports(
    config: LinkConfig,
    transport: Transport | None,
    compat_transport: Transport | None,
    vehicle_index: int = 0,
    members: int = 3,
) -> tuple[Transport, Transport | None]:
    """The J2735 transport (``open_transport``) and, with ``config.compat``, the IPv4
    socket (each unless injected); nothing stays open when the second cannot be opened."""
    tx = transport if transport is not None else open_transport(config, vehicle_index, members)
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
        self._tx, self._tx4 = _open_transports(
            config, transport, compat_transport, vehicle_index, len(temp_ids)
        )
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
            "transport": self.config.transport,
            **(
                {"ros2_topic": self.config.ros2_topic, "ros2_domain": self.config.ros2_domain}
                if self.config.transport == "ros2"
                else {}
            ),
            "vehicle_index": self.vehicle_index,
            "temp_id": self.sender.temp_id.hex(),
            "drop_at": self.drop_at,
            "loss": asdict(self.loss) if self.loss is not None else None,
            "latency_emulated": False,
            "auth": self._auth_metadata(),
            "time_tolerance_s": self.config.time_tolerance_s,
            "position_jumps": dict(self.receiver._jumps.jumps),
            "auth_mismatch": dict(self.receiver.auth_mismatch),
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
            "certificates_cached": a.certificates_cached,
            "revoked": len(a.credentials.revoked),
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

    def send_complete(self, now: float, repeat: int = 3) -> None:
        """Broadcast that the leader completed its scenario (``repeat`` copies, each its
        own generation time; signed with ``PSID_COMPLETE`` when authenticating)."""
        for i in range(repeat):
            t = now + i * 1e-3
            data = make_complete(t, self.vehicle_index)
            if self.auth is not None:
                data = self.auth.sign(data, PSID_COMPLETE, t)
            self._send(self._tx, data)

    def poll(self, now: float, budget_s: float | None = None) -> list[Received]:
        """Messages waiting, decoded and filtered, received at ``now`` (seconds).

        With ``budget_s`` the poll takes at most that long (monotonic clock): it reads and
        classifies for up to ``READ_SHARE`` of it and leaves the rest in the socket buffers
        for the next poll (the sockets take turns in chunks of ``POLL_CHUNK``; the kernel
        drops what overflows them), then verifies signatures
        as ``Receiver.handle_batch`` schedules them until the budget is spent, so a flood
        of datagrams cannot stall the caller's control loop nor starve a genuine sender.
        None: every datagram waiting.
        """
        out: list[Received] = []
        pending: list[_Pending] = []
        transports = [self._tx] if self._tx4 is None else [self._tx, self._tx4]
        t0 = self._clock()
        deadline = math.inf if budget_s is None else t0 + budget_s
        read_deadline = math.inf if budget_s is None else t0 + READ_SHARE * budget_s
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
                self.receiver.prepare_batch([(d.data, d.source) for d in dgrams], now, pending, out)
            if transports and self._clock() >= read_deadline:
                self.counters.budget_hits += 1
                break
        self.receiver.verify_batch(pending, now, out, deadline=deadline, clock=self._clock)
        return out

    def take_alerts(self, now: float | None = None) -> list[str]:
        """Operator lines since the last call (floods, auth disagreement, clock offsets,
        position jumps, impersonation), each at most once per ``guards.ALERT_PERIOD_S``
        (a clock offset over half the tolerance: once a minute per member). ``now``: the
        shared clock (s); default the last receive time."""
        r = self.receiver
        t = r.last_t_rx if now is None else now
        half = self.config.time_tolerance_s / 2
        for i, o in sorted(self.clock_offsets(t).items()):
            if abs(o) > half:
                r.alerts.raise_(
                    "skew",
                    i,
                    t,
                    f"vehicle {self.vehicle_index}: vehicle {i}'s clock is {abs(o):.2f} s "
                    f"{'ahead of' if o > 0 else 'behind'} this vehicle's (tolerance "
                    f"{self.config.time_tolerance_s:g} s)",
                    period_s=SKEW_ALERT_PERIOD_S,
                )
        return r.alerts.take()

    def clock_offsets(self, now: float) -> dict[int, float]:
        """Each member's clock minus ours (s) as heard lately."""
        r = self.receiver
        out = {}
        for i, _ in r.temp_ids:
            o = r.skew.offset(i, now)
            if o is not None and i != self.vehicle_index:
                out[i] = o
        return out

    def start_refusal(self, now: float) -> str:
        """Why the convoy must not start ("" = it may): a member using V2V authentication
        differently from us, or a clock further off ours than the link's tolerance."""
        r = self.receiver
        if r.auth_mismatch:
            return next(iter(r.auth_mismatch.values()))
        tol = self.config.time_tolerance_s
        for i, o in sorted(self.clock_offsets(now).items()):
            if abs(o) > tol:
                return (
                    f"vehicle {self.vehicle_index}: vehicle {i}'s clock is {abs(o):.2f} s "
                    f"{'ahead of' if o > 0 else 'behind'} this vehicle's, more than the "
                    f"{tol:g} s tolerance ([v2v] replay_window_s): synchronise the clocks "
                    "(NTP, GPS)"
                )
        return ""

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
    ros2: tuple[str, int] | None = None,
    ros2_wait_s: float = 3.0,
) -> int:
    """Send a convoy-wide abort as an operator (``event_flags.car = -1``).

    The compatibility-format JSON with ``abort: true`` goes to the IPv6 BSM group (our
    vehicles) and, with ``compat_enabled``, to the IPv4 group (vehicles running the
    original implementation). Sent ``repeat`` times ``interval_s`` apart, since multicast
    has no acknowledgement. ``now`` (seconds, default the system clock) stamps the message.
    With ``security.auth`` the abort is a signed SPDU (PSID ``PSID_ABORT``; each repeat has its own
    generation time), and only on the IPv6 group. With ``ros2`` = (topic, DDS domain) — a
    convoy whose V2V goes over ROS 2 — it also goes on that topic (``comms.dds``), once DDS
    discovery has matched a reader or ``ros2_wait_s`` has passed. Returns the number of
    datagrams sent.
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
        if ros2 is not None:
            from openconvoy.comms.dds import DdsTransport

            dds = DdsTransport(iface, ros2[0], ros2[1], vehicle_id=-1)
            socks.append(dds)
            dds.wait_for_readers(ros2_wait_s)
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
    "make_complete",
    "parse_complete",
    "schedule",
    "DUPLICATE_WINDOW_S",
    "POLL_CHUNK",
]
