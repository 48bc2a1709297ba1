"""The pymavlink connection under ``MavlinkLink``: open, notice loss, reopen, read, close.

Knows URLs and sockets, nothing about vehicles. pymavlink's TCP link reports a peer's EOF
by printing and returning no data forever (``autoreconnect`` off): its hooks are replaced
so that EOF and resets mark the connection ``lost`` instead. A reopen for the runner's
loop happens in a helper thread (a TCP connect can take seconds) and is installed by the
next ``install_pending`` on the owner's thread.
"""

from __future__ import annotations

import math
import socket
import threading
from collections.abc import Callable
from typing import Any

from openconvoy.bridge.link import LinkLost, StatusCallback
from openconvoy.bridge.mavlink import protocol as mp

RECEIVE_BUFFER_BYTES = 8 << 20
"""The socket receive buffer asked for (the kernel caps it at ``net.core.rmem_max``). A
real PX4 sends ~200 messages/s on its onboard link (shared/sitl-px4: TIMESYNC, ALTITUDE,
VFR_HUD, GPS_RAW_INT, ... at their default rates besides what we request); at the default
~208 KiB a pause of the loop of about a second overflows the buffer and the kernel drops
what comes next, such as PX4's "Failsafe activated" text. With the buffer raised, the
messages of a pause wait for the next read (up to rmem_max: 4 MiB holds ~20 s)."""


class MavConnection:
    """One MAVLink connection by URL, reopenable.

    Attributes:
        conn: the pymavlink connection (None while closed).
        eof: the peer closed or reset it, or reading failed.
        lost_reason: why (one line, "" while not lost).
    """

    def __init__(
        self,
        url: str,
        baud: int,
        source_system: int,
        source_component: int,
        status: StatusCallback,
    ) -> None:
        self.url = url
        self.baud = baud
        self.source_system = source_system
        self.source_component = source_component
        self._status = status
        self.conn: Any = None
        self._pending: list[Any] = []  # a connection opened by the reopen thread
        self._opener: threading.Thread | None = None
        self.reset()

    def reset(self) -> None:
        """Forget a loss (before opening again)."""
        self.eof = False
        self.lost_reason = ""
        self._t_gcs_heartbeat = -math.inf

    @property
    def lost(self) -> bool:
        """No usable connection (EOF/reset, read error, or none open)."""
        return self.eof or self.conn is None

    @property
    def reopening(self) -> bool:
        """A background reopen is running or its connection waits to be installed."""
        return bool(self._pending) or (self._opener is not None and self._opener.is_alive())

    def open(self) -> None:
        """Open now (may block: TCP connect); raises ``LinkLost``."""
        self._install(self._make_connection())

    def _make_connection(self) -> Any:
        """A new pymavlink connection (may block: TCP connect); raises ``LinkLost``."""
        kwargs: dict[str, Any] = dict(
            source_system=self.source_system,
            source_component=self.source_component,
            autoreconnect=False,
        )
        if self.url.startswith("tcp:"):
            kwargs["retries"] = 1  # one attempt; reconnecting is the caller's decision
        try:
            conn = mp.mavutil.mavlink_connection(self.url, baud=self.baud, **kwargs)
        except OSError as exc:
            raise LinkLost(f"cannot open MAVLink link {self.url}: {exc}") from exc
        return conn

    def _install(self, conn: Any) -> None:
        # pymavlink's TCP link prints and "reconnects" (a no-op without autoreconnect) on EOF
        # and returns no data, forever: hook it so EOF marks the link lost instead.
        conn.handle_eof = lambda: self.mark_lost("connection closed by the vehicle (EOF)")
        conn.handle_disconnect = lambda: self.mark_lost("connection reset by the vehicle")
        sock = getattr(conn, "port", None)
        if isinstance(sock, socket.socket):  # UDP and TCP links; not serial ports
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            except OSError:
                pass  # the default buffer still works
        self.conn = conn

    def mark_lost(self, reason: str) -> None:
        """Latch the loss (one status line the first time)."""
        if not self.eof:
            self._status(f"MAVLink link {self.url} lost: {reason}")
        self.eof = True
        self.lost_reason = reason

    def reopen_in_background(self) -> None:
        """Open a new connection in a helper thread; ``install_pending`` installs it.
        A failed open comes as a status line."""

        def open_in_background() -> None:
            try:
                self._pending.append(self._make_connection())
            except LinkLost as exc:
                self._status(f"reconnect failed: {exc}")

        self._opener = threading.Thread(
            target=open_in_background, name="mavlink-reopen", daemon=True
        )
        self._opener.start()

    def install_pending(self) -> None:
        """Install a connection the reopen thread made (while none is open)."""
        if self._pending and self.conn is None:
            self._install(self._pending.pop())
            self._status(f"MAVLink link {self.url} reopened; waiting for the vehicle's heartbeat")

    def send_gcs_heartbeat(self, now: float) -> None:
        """Our GCS heartbeat, at most once a second (clock ``now``, s): autopilots watch
        for it (ArduPilot's and PX4's GCS failsafes)."""
        if now - self._t_gcs_heartbeat >= 1.0:
            self._t_gcs_heartbeat = now
            m = mp.mav()
            self.conn.mav.heartbeat_send(
                mp.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE
            )

    def drain(self, handle: Callable[[Any], None], max_messages: int = 5000) -> None:
        """Hand every pending message to ``handle``; a read error marks the link lost."""
        if self.eof:
            return  # a closed TCP link would report EOF on every read: stop reading
        for _ in range(max_messages):
            try:
                msg = self.conn.recv_msg()
            except OSError as exc:
                self.mark_lost(str(exc))
                return
            if msg is None or self.eof:
                return
            handle(msg)

    def close(self) -> None:
        """Close the connection and any reopened one not yet installed (idempotent)."""
        while self._pending:
            try:
                self._pending.pop().close()
            except OSError:
                pass
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
