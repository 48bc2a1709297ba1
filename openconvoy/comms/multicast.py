"""UDP multicast sockets for V2V: IPv6 for J2735 BSMs, IPv4 for the compatibility format.

Both are non-blocking: ``recv_all()`` returns every datagram waiting and never blocks, so
a control loop can poll them once per tick. Multicast loop is on, so several processes on
one host (or one network namespace) hear each other; the receiver filters its own echoes
by content (temporary ID / convoy position), not here.

Never point these at a real interface in tests: see ``netns`` for private namespaces.
``MemoryBus`` is an in-process stand-in with the same interface, for unit tests.
"""

from __future__ import annotations

import errno
import ipaddress
import socket
import struct
from collections import deque
from collections.abc import Iterable
from typing import NamedTuple, Protocol, TypeVar

from openconvoy.core.errors import ConfigError, LinkError

#: Default IPv6 group: ff15:: is a transient (flag 1), site-local (scope 5) group, so
#: routers keep it inside the site even if the hop limit were raised.
DEFAULT_GROUP = "ff15::4f43"
DEFAULT_PORT = 4200
DEFAULT_HOP_LIMIT = 1

#: Enough socket buffer for a roadside unit hearing ~1000 vehicles at 10 Hz between polls
#: (Linux doubles it, and holds ~10,000 small datagrams in that). A control loop wants far
#: less: see ``V2V_RCVBUF_BYTES``.
RCVBUF_BYTES = 4 * 1024 * 1024
#: A vehicle's V2V socket buffer: ~600 small datagrams, a second of a 60-vehicle convoy's
#: BSMs. Under a flood the loop cannot read in time, a big buffer turns into seconds of
#: latency for the convoy's own messages (10,000 queued datagrams read at ~5,000/s are 2 s
#: old; measured by ``benchmarks/bench_flood.py``: followers stopped on stale messages);
#: this one bounds it to about a tenth of a second, and the excess is lost instead.
V2V_RCVBUF_BYTES = 256 * 1024
#: Upper bound on datagrams returned by one ``recv_all``. A control loop bounds its
#: receiving by time instead (``V2V.poll``'s budget), reading small batches.
MAX_BATCH = 10_000
MAX_DATAGRAM = 65_535


class Datagram(NamedTuple):
    """One received datagram: payload and sender address (text). (A named tuple: built for
    every datagram, and cheaper to build than a frozen dataclass.)"""

    data: bytes
    source: str


class Transport(Protocol):
    """What ``V2V`` needs from a socket."""

    def send(self, data: bytes) -> None:
        """Send one datagram to the group (errors raise ``OSError``)."""

    def recv_all(self, max_batch: int = MAX_BATCH) -> list[Datagram]:
        """Datagrams waiting (at most ``max_batch``), oldest first; empty when none.
        Never blocks."""

    def close(self) -> None:
        """Release the socket."""


def multicast_scope(group: ipaddress.IPv6Address) -> int:
    """The scope field of an IPv6 multicast address (RFC 4291: 2 link, 5 site, 14 global)."""
    return group.packed[1] & 0x0F


def interface_index(iface: str) -> int:
    """Kernel index of network interface ``iface`` (``ValueError`` naming it if unknown)."""
    try:
        return socket.if_nametoindex(iface)
    except OSError:
        raise ConfigError(f"no network interface named {iface!r}") from None


def _drain(sock: socket.socket, max_batch: int) -> list[Datagram]:
    out: list[Datagram] = []
    while len(out) < max_batch:
        try:
            data, addr = sock.recvfrom(MAX_DATAGRAM)
        except BlockingIOError:
            break
        except OSError as exc:
            # An ICMP error queued on the socket surfaces once on a later call; skip it.
            if exc.errno in (errno.ECONNREFUSED, errno.EHOSTUNREACH, errno.ENETUNREACH):
                continue
            raise
        out.append(Datagram(data, str(addr[0])))
    return out


_S = TypeVar("_S", bound="_MulticastSocket")


class _MulticastSocket:
    """What both multicast sockets share once bound: ``_sock`` and its destination."""

    _sock: socket.socket
    _dest: tuple

    def send(self, data: bytes) -> None:
        self._sock.sendto(data, self._dest)

    def recv_all(self, max_batch: int = MAX_BATCH) -> list[Datagram]:
        return _drain(self._sock, max_batch)

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()

    def __enter__(self: _S) -> _S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Ipv6Multicast(_MulticastSocket):
    """A UDP/IPv6 multicast socket joined to ``group`` on interface ``iface``.

    Args:
        iface: interface name (e.g. ``wlan0``); sending and joining both use it.
        group: IPv6 multicast group (default ``ff15::4f43``).
        port: UDP port (default 4200).
        hop_limit: IPv6 multicast hop limit (default 1: one link).
        loop: deliver our own datagrams to sockets on this host (default on).
        rcvbuf_bytes: receive buffer asked of the kernel (``RCVBUF_BYTES``).
    """

    def __init__(
        self,
        iface: str,
        group: str = DEFAULT_GROUP,
        port: int = DEFAULT_PORT,
        hop_limit: int = DEFAULT_HOP_LIMIT,
        loop: bool = True,
        rcvbuf_bytes: int = RCVBUF_BYTES,
    ) -> None:
        addr = ipaddress.ip_address(group)
        if addr.version != 6 or not addr.is_multicast:
            raise ConfigError(f"{group!r} is not an IPv6 multicast group")
        if not 0 <= port <= 65535:
            raise ConfigError(f"port must be in 0..65535, got {port}")
        if not 0 <= hop_limit <= 255:
            raise ConfigError(f"hop limit must be in 0..255, got {hop_limit}")
        self.iface, self.group, self.port, self.hop_limit = iface, str(addr), port, hop_limit
        self.ifindex = interface_index(iface)
        sock = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            # Several members on one host share the group and port.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            # Bound to the group, not ::, so datagrams for other groups on this port that
            # another socket joined are not delivered here.
            # Interface- and link-local scoped groups (ffx1::, ffx2::) need the interface
            # as scope id to bind; wider scopes (ff15:: site-local) must not have one.
            scope = self.ifindex if multicast_scope(addr) <= 2 else 0
            sock.bind((self.group, port, 0, scope))
            mreq = addr.packed + struct.pack("@I", self.ifindex)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, mreq)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, self.ifindex)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hop_limit)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, int(loop))
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise LinkError(
                f"cannot use IPv6 multicast group {self.group} port {port} on {iface}: "
                f"{exc.strerror or exc} (does {iface} support IPv6 multicast?)"
            ) from None
        self._sock = sock
        self._dest = (self.group, port, 0, self.ifindex)

    @property
    def port_bound(self) -> int:
        """The local port (useful with ``port=0``)."""
        return self._sock.getsockname()[1]


class Ipv4Multicast(_MulticastSocket):
    """A UDP/IPv4 multicast socket (the compatibility format: 224.0.0.1:5004, TTL 1)."""

    def __init__(
        self,
        iface: str,
        group: str = "224.0.0.1",
        port: int = 5004,
        ttl: int = 1,
        loop: bool = True,
        rcvbuf_bytes: int = RCVBUF_BYTES,
    ) -> None:
        addr = ipaddress.ip_address(group)
        if addr.version != 4 or not addr.is_multicast:
            raise ConfigError(f"{group!r} is not an IPv4 multicast group")
        if not 0 <= ttl <= 255:
            raise ConfigError(f"TTL must be in 0..255, got {ttl}")
        self.iface, self.group, self.port, self.ttl = iface, str(addr), port, ttl
        self.ifindex = interface_index(iface)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
            sock.bind((self.group, port))
            # struct ip_mreqn {group, local address (any), ifindex}: selects the interface
            # by index, so it works whatever IPv4 address the interface has.
            mreqn = addr.packed + bytes(4) + struct.pack("@i", self.ifindex)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreqn)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, mreqn)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, ttl)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, int(loop))
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise LinkError(
                f"cannot use IPv4 multicast group {self.group} port {port} on {iface}: "
                f"{exc.strerror or exc}"
            ) from None
        self._sock = sock
        self._dest = (self.group, port)


class MemoryBus:
    """An in-process multicast "link" for unit tests: every endpoint hears every send,
    its own included (like multicast loop). An endpoint made with a ``capacity`` holds at
    most that many datagrams and drops what arrives beyond (``dropped``), as a kernel
    socket buffer does."""

    def __init__(self) -> None:
        self._queues: list[deque[Datagram]] = []
        self._capacity: dict[int, int] = {}
        self.dropped = 0

    def endpoint(self, name: str = "mem", capacity: int | None = None) -> MemoryEndpoint:
        """A new endpoint (a ``Transport``) attached to this bus."""
        q: deque[Datagram] = deque()
        self._queues.append(q)
        if capacity is not None:
            self._capacity[id(q)] = capacity
        return MemoryEndpoint(self, q, name)

    def inject(self, data: bytes, source: str = "injected") -> None:
        """Deliver ``data`` to every endpoint, as if a foreign station had sent it."""
        for q in self._queues:
            cap = self._capacity.get(id(q))
            if cap is not None and len(q) >= cap:
                self.dropped += 1
                continue
            q.append(Datagram(bytes(data), source))

    def inject_many(self, items: Iterable[bytes], source: str = "injected") -> None:
        for data in items:
            self.inject(data, source)

    def _detach(self, q: deque[Datagram]) -> None:
        self._queues = [x for x in self._queues if x is not q]
        self._capacity.pop(id(q), None)


class MemoryEndpoint:
    """One endpoint of a ``MemoryBus`` (see there)."""

    def __init__(self, bus: MemoryBus, queue: deque[Datagram], name: str) -> None:
        self._bus, self._queue, self.name = bus, queue, name

    def send(self, data: bytes) -> None:
        self._bus.inject(data, self.name)

    def recv_all(self, max_batch: int = MAX_BATCH) -> list[Datagram]:
        q = self._queue
        return [q.popleft() for _ in range(min(max_batch, len(q)))]

    def close(self) -> None:
        self._bus._detach(self._queue)
