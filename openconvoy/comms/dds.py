"""V2V over ROS 2 (``[v2v] transport = "ros2"``, ``deploy --v2v ros2``): the same signed
BSM/SPDU bytes as IPv6 multicast, one DDS sample each, on a ROS 2 topic that any ROS 2
node of the lab's DDS domain can read — for labs whose vehicles already share one.

The vehicle needs no ROS install: this speaks DDS directly through Cyclone DDS
(``cyclonedds``, the ``px4dds`` extra) with ROS 2's names, as ``bridge.px4dds`` does: the
topic ``/openconvoy/v2v`` is the DDS topic ``rt/openconvoy/v2v`` (rmw's ``ros_topic_prefix``
``rt``), the type ``openconvoy_msgs/msg/V2VBytes`` is the DDS type
``openconvoy_msgs::msg::dds_::V2VBytes_`` (rosidl's DDS mangling), serialized as XCDR1
(Cyclone's default for these types, and what ROS 2's rmw implementations use), so an rclpy
node with our ``openconvoy_msgs`` built (``make ros2``) subscribes to it as to any topic.

The type is ours (``openconvoy/msg/V2VBytes.msg``, the one ``deploy --bag`` records V2V
datagrams as), not ``std_msgs/msg/UInt8MultiArray``: that file itself says it "is
deprecated as of Foxy" and recommends "a semantically meaningful message"; ours says which
vehicle sent the bytes and when, and a ``ros2 bag record`` of the live topic reads as our
own bags do. On the wire ``direction`` is ``"tx"`` and ``vehicle_id`` the sender's claim —
information only: the receiver trusts nothing but the signed bytes in ``data``, which go
through the same decoding, verification, counting and dropping as a multicast datagram
(``comms.v2v.V2V.poll``). A sample Cyclone cannot deserialize is counted (``bad_samples``)
and dropped.

QoS for V2V: best effort (a BSM is worth nothing once the next one is out, as on the air),
volatile, keep last ``depth_for(convoy size)`` (a bounded queue between polls, as the
multicast socket's buffer; under a flood the oldest are lost, never the control loop's time).

DDS stays on the V2V interface: Cyclone is configured to use ``iface`` only (the one
``--iface`` names for multicast), so its discovery and data go where multicast V2V would,
and in tests and the demo that is a veth inside a private network namespace.
"""

# No ``from __future__ import annotations``: cyclonedds reads these annotations as objects.

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from openconvoy.comms.multicast import MAX_BATCH, Datagram
from openconvoy.core.errors import ConfigError, DependencyMissing, LinkError

INSTALL_HINT = "V2V over ROS 2 needs Cyclone DDS: pip install 'openconvoy[px4dds]'"
try:
    from cyclonedds.core import (
        InstanceState,
        Policy,
        Qos,
        ReadCondition,
        SampleState,
        ViewState,
        WaitSet,
    )
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as t
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
except ModuleNotFoundError:  # an optional dependency: say how to get it
    raise DependencyMissing(INSTALL_HINT) from None

if TYPE_CHECKING:  # cyclonedds' sequence type is not generic to mypy; a list at runtime
    U8Seq = list[int]
else:
    U8Seq = t.sequence[t.uint8]

DEFAULT_TOPIC = "/openconvoy/v2v"
DEFAULT_DOMAIN = 0
PER_MEMBER = 8
"""Samples kept per convoy member (``depth_for``): with 10 Hz BSMs and plans beside them,
about 0.4 s of the convoy's messages — several polls of a 20 Hz loop."""


def depth_for(members: int) -> int:
    """The reader's keep-last depth for a convoy of ``members`` vehicles (at least 16).

    Bounded on purpose: DDS's keep-last drops the *oldest* sample when full, so a vehicle
    that polls late (its loop starting, a loaded machine) reads what was sent last, not a
    backlog of seconds — such a backlog, read oldest first, is all stale, and its clock
    offsets stop the convoy start (measured: a deploy that began polling 12 s after its
    peers read only samples 1.7 s old and refused to start with a depth of 256)."""
    return max(16, PER_MEMBER * members)


DEPTH = depth_for(3)


def dds_topic(ros_topic: str) -> str:
    """The DDS topic of an absolute ROS 2 topic name: ``/openconvoy/v2v`` → ``rt/openconvoy/v2v``
    (``ConfigError`` naming the rule if it is not a valid ROS 2 topic name)."""
    name = ros_topic.strip()
    parts = name.lstrip("/").split("/")
    ok = name.startswith("/") and all(
        p and (p[0].isalpha() or p[0] == "_") and all(c.isalnum() or c == "_" for c in p)
        for p in parts
    )
    if not ok:
        raise ConfigError(
            f"{ros_topic!r} is not an absolute ROS 2 topic name (e.g. /openconvoy/v2v: "
            "'/'-separated parts of letters, digits and '_', not starting with a digit)"
        )
    return "rt/" + "/".join(parts)


def interface_config(iface: str) -> str:
    """Cyclone's configuration for a domain used only on network interface ``iface``."""
    if not iface or any(c in iface for c in "<>'\"&"):
        raise ConfigError(f"{iface!r} is not a network interface name")
    return (
        "<CycloneDDS><Domain id='any'><General>"
        f"<Interfaces><NetworkInterface name='{iface}'/></Interfaces>"
        "</General></Domain></CycloneDDS>"
    )


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/msg/Time."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/msg/Header."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class V2VBytes(IdlStruct, typename="openconvoy_msgs::msg::dds_::V2VBytes_"):
    """openconvoy/msg/V2VBytes.msg, field for field."""

    header: Header = field(default_factory=Header)
    vehicle_id: t.int32 = 0
    direction: str = ""
    data: U8Seq = field(default_factory=list)


def to_sample(data: bytes, vehicle_id: int, t_s: float) -> Any:
    """A ``V2VBytes`` sample carrying ``data`` sent by ``vehicle_id`` at wall time ``t_s`` (s)."""
    sec = int(t_s // 1)
    stamp = Time(sec=sec, nanosec=min(int((t_s - sec) * 1e9), 999_999_999))
    return V2VBytes(Header(stamp, ""), int(vehicle_id), "tx", list(data))


_DOMAINS: dict[int, Any] = {}


class Waiter:
    """Blocks until one of its readers has a sample (a Cyclone ``WaitSet`` on a
    ``ReadCondition`` per reader): a loop that takes what arrives wakes once per arrival
    instead of polling."""

    def __init__(self, dp: DomainParticipant, readers: list[DataReader]) -> None:
        self._ws = WaitSet(dp)
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        self._conditions = [ReadCondition(r, mask) for r in readers]
        for c in self._conditions:
            self._ws.attach(c)

    def wait(self, timeout_s: float) -> bool:
        """Return when a reader has data (True) or after ``timeout_s`` (s; False)."""
        return bool(self._ws.wait(max(0, int(timeout_s * 1e9))))


class DdsTransport:
    """A ``comms.multicast.Transport`` over a ROS 2 topic of DDS domain ``domain_id``, Cyclone
    kept on network interface ``iface`` (``interface_config``); ``vehicle_id`` and ``wall``
    (s) stamp what is sent; ``depth`` samples are kept between polls (``depth_for``).
    ``recv_all`` never blocks; a datagram's source is
    ``dds:<writer handle>`` (one per sending vehicle). With ``read=False`` it only sends (no
    reader: one that other senders' ``wait_for_readers`` would count, as ``bsm send``)."""

    def __init__(
        self,
        iface: str,
        topic: str = DEFAULT_TOPIC,
        domain_id: int = DEFAULT_DOMAIN,
        vehicle_id: int = 0,
        wall: Callable[[], float] = time.time,
        depth: int = DEPTH,
        read: bool = True,
    ) -> None:
        if not 0 <= domain_id <= 232:
            raise ConfigError(f"DDS domain id must be in 0..232, got {domain_id}")
        name = dds_topic(topic)
        config = interface_config(iface)
        self.topic, self.domain_id, self.iface = topic, domain_id, iface
        self.vehicle_id, self.wall = vehicle_id, wall
        self.bad_samples = 0
        self._waitset: Any = None  # made by the first ``wait``
        qos = Qos(
            Policy.Reliability.BestEffort,
            Policy.Durability.Volatile,
            Policy.History.KeepLast(depth),
        )
        try:
            # One Domain object per id and process (Cyclone refuses a second): it carries
            # the configuration, so it lives as long as the process.
            if domain_id not in _DOMAINS:
                _DOMAINS[domain_id] = Domain(domain_id, config)
            self._dp: Any = DomainParticipant(domain_id)
            topic_: Any = Topic(self._dp, name, V2VBytes)
            self._writer = DataWriter(self._dp, topic_, qos=qos)
            self._reader: Any = DataReader(self._dp, topic_, qos=qos) if read else None
        except Exception as exc:  # noqa: BLE001 (cyclonedds raises plain DDSException)
            raise LinkError(
                f"cannot use DDS domain {domain_id} on {iface} for V2V topic {topic}: {exc} "
                "(with --link px4-dds --dds-localhost the domain is configured for loopback "
                "already: give [v2v] ros2_domain another id)"
            ) from None

    def send(self, data: bytes) -> None:
        """Publish one datagram (an ``OSError`` when the participant is closed)."""
        if self._dp is None:
            raise OSError("V2V DDS participant closed")
        self._writer.write(to_sample(data, self.vehicle_id, self.wall()))

    def wait_for_readers(self, timeout_s: float, at_least: int = 1) -> int:
        """Wait up to ``timeout_s`` (s) until ``at_least`` readers other than our own have
        matched our writer (DDS discovery; best-effort samples written before are lost to
        them); returns how many have. For one-shot senders such as ``openconvoy abort``."""
        deadline = time.monotonic() + timeout_s
        while True:
            ours = 1 if self._reader is not None else 0
            n = max(0, len(self._writer.get_matched_subscriptions()) - ours)
            if n >= at_least or time.monotonic() >= deadline:
                return n
            time.sleep(0.02)

    def wait(self, timeout_s: float) -> bool:
        """Block until a sample is waiting or ``timeout_s`` (s) has passed; True if one is
        (``Waiter`` on our reader: a listener wakes once per arrival instead of polling —
        the transport has no file descriptor for ``select``). An ``OSError`` when the
        participant is closed."""
        if self._dp is None:
            raise OSError("V2V DDS participant closed")
        if self._reader is None:
            raise OSError("V2V DDS transport opened with read=False")
        if self._waitset is None:
            self._waitset = Waiter(self._dp, [self._reader])
        return self._waitset.wait(timeout_s)

    def recv_all(self, max_batch: int = MAX_BATCH) -> list[Datagram]:
        """Samples waiting (at most ``max_batch``), oldest first; bad ones counted, dropped."""
        if self._dp is None:
            raise OSError("V2V DDS participant closed")
        out: list[Datagram] = []
        while self._reader is not None and len(out) < max_batch:
            try:
                samples = self._reader.take(N=min(64, max_batch - len(out)))
            except Exception:  # noqa: BLE001 (cyclonedds raises plain Exceptions on bad CDR)
                self.bad_samples += 1  # the undecodable sample is gone: read on next poll
                break
            if not samples:
                break
            for sample in samples:
                if isinstance(sample, V2VBytes):  # an InvalidSample (a writer left) has no data
                    s: Any = sample
                    handle = getattr(s.sample_info, "publication_handle", 0)
                    out.append(Datagram(bytes(s.data), f"dds:{handle:x}"))
        return out

    def close(self) -> None:
        """Delete the participant (its reader and writer with it); idempotent."""
        self._waitset = None  # before its participant: its own delete detaches from a live one
        if self._dp is not None:
            self._dp.__del__()  # cyclonedds has no public delete; this one is idempotent
        self._dp = None
