"""A scripted autopilot at the edge of the system: real MAVLink bytes (pymavlink's encoder
and parser) over a UDP socket, a TCP socket or a pseudo-terminal, with behaviour set by the
test (which mode arming ends in, whether commands are answered, what it streams).

It is not a vehicle model (``bridge.simvehicle.vehicle`` is): it records every message the link
sends, so tests can check the fields byte for byte, and it can do things a model should not
(never answer a command, switch mode right after arming like ArduPilot's RC mode switch).
"""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp


class _UdpPort:
    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.peer: tuple[str, int] | None = None
        self.url = f"udpout:127.0.0.1:{self.sock.getsockname()[1]}"

    def read(self) -> bytes:
        try:
            data, self.peer = self.sock.recvfrom(65536)
            return data
        except BlockingIOError:
            return b""

    def write(self, data: bytes) -> None:
        if self.peer is not None:
            self.sock.sendto(data, self.peer)

    def close(self) -> None:
        self.sock.close()


class _TcpPort:
    """Listens; accepts one client at a time (a new client replaces the old)."""

    def __init__(self) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(4)
        self.server.setblocking(False)
        self.client: socket.socket | None = None
        self.url = f"tcp:127.0.0.1:{self.server.getsockname()[1]}"

    def read(self) -> bytes:
        try:
            client, _ = self.server.accept()
            client.setblocking(False)
            if self.client is not None:
                self.client.close()
            self.client = client
        except BlockingIOError:
            pass
        if self.client is None:
            return b""
        try:
            data = self.client.recv(65536)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:  # closed by the link
            self.client.close()
            self.client = None
        return data

    def write(self, data: bytes) -> None:
        if self.client is not None:
            try:
                self.client.sendall(data)
            except OSError:
                self.client.close()
                self.client = None

    def drop_client(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    def close(self) -> None:
        self.drop_client()
        self.server.close()


class _PtyPort:
    """The autopilot's end of a pseudo-terminal pair; the link opens ``url`` (the slave)."""

    def __init__(self) -> None:
        import tty

        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        self.url = os.ttyname(self.slave)

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return b""

    def write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class _Writer:
    def __init__(self, port: Any) -> None:
        self.port = port

    def write(self, data: bytes) -> None:
        self.port.write(bytes(data))


@dataclass
class EdgeAutopilot:
    """A scripted autopilot (see the module docstring). Call ``start()``, ``stop()``.

    Attributes:
        transport: ``"udp"``, ``"tcp"`` or ``"pty"``.
        autopilot: ``"ardupilot"`` or ``"px4"``.
        heading_deg: compass heading it reports (ATTITUDE, GLOBAL_POSITION_INT hdg).
        speed_mps: forward speed it reports.
        rate_hz: telemetry rate (GLOBAL_POSITION_INT and ATTITUDE).
        heartbeat_hz: heartbeat rate.
        answer_commands: COMMAND_ACK every COMMAND_LONG (False: never answer).
        mode_after_arm: a mode it switches to on its own right after arming (and again
            ``mode_switch_repeats`` times after the guided mode is requested back).
        send_position: stream GLOBAL_POSITION_INT (False: ATTITUDE only).
        arm_refusals: refuse this many arm commands first (result 4 and a STATUSTEXT).
        mode_at: (t, mode): switch to ``mode`` on its own at ``t`` s after start, once (the
            RC mode switch's first reading at boot).
        arm_modes: the mode it was in at each arm command (filled in).
    """

    transport: str = "udp"
    autopilot: str = "ardupilot"
    heading_deg: float = 90.0
    speed_mps: float = 0.0
    rate_hz: float = 20.0
    heartbeat_hz: float = 10.0
    answer_commands: bool = True
    mode_after_arm: str | None = None
    mode_switch_repeats: int = 0
    send_position: bool = True
    arm_refusals: int = 0
    mode_at: tuple[float, str] | None = None
    arm_modes: list[str] = field(default_factory=list)
    system_id: int = 1
    mode: str = ""
    armed: bool = False
    received: list[tuple[float, Any]] = field(default_factory=list)
    extra: list[Callable[[Any, float], None]] = field(default_factory=list)
    """Called every loop with (pymavlink MAVLink encoder, t) to send more messages."""

    def __post_init__(self) -> None:
        self.port = {"udp": _UdpPort, "tcp": _TcpPort, "pty": _PtyPort}[self.transport]()
        self.url = self.port.url
        self.mav = mp.mav().MAVLink(_Writer(self.port), srcSystem=self.system_id, srcComponent=1)
        self.parser = mp.mav().MAVLink(None)
        self.parser.robust_parsing = True
        if not self.mode:
            self.mode = "HOLD" if self.autopilot == "ardupilot" else "LOITER"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._switches_left = 0
        self._switch_at = math.inf
        self.lock = threading.Lock()
        self.t0 = time.monotonic()

    # ------------------------------------------------------------------ control

    def start(self) -> EdgeAutopilot:
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.port.close()

    def messages(self, kind: str) -> list[Any]:
        with self.lock:
            return [m for _, m in self.received if m.get_type() == kind]

    def clear(self) -> None:
        with self.lock:
            self.received.clear()

    # ------------------------------------------------------------------ internals

    def _custom_mode(self) -> int:
        if self.autopilot == "px4":
            return mp.px4_custom_mode(*mp.PX4_MODE_NUMBERS[self.mode])
        return mp.ROVER_MODE_NUMBERS[self.mode]

    def _loop(self) -> None:
        m = mp.mav()
        ap = mp.AUTOPILOT_PX4 if self.autopilot == "px4" else mp.AUTOPILOT_ARDUPILOT
        t_hb = t_tel = -math.inf
        while not self._stop.is_set():
            t = time.monotonic() - self.t0
            data = self.port.read()
            if data:
                for msg in self.parser.parse_buffer(data) or []:
                    self._on_message(msg, t)
            if self.mode_at is not None and t >= self.mode_at[0]:
                self.mode, self.mode_at = self.mode_at[1], None
            if t >= self._switch_at:
                self._switch_at = math.inf
                self.mode = self.mode_after_arm or self.mode
            if t - t_hb >= 1.0 / self.heartbeat_hz:
                t_hb = t
                base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
                    m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
                )
                self.mav.heartbeat_send(
                    mp.MAV_TYPE_GROUND_ROVER, ap, base, self._custom_mode(), m.MAV_STATE_ACTIVE
                )
            if t - t_tel >= 1.0 / self.rate_hz:
                t_tel = t
                ms = int(t * 1000)
                yaw = math.radians(self.heading_deg)
                vn, ve = self.speed_mps * math.cos(yaw), self.speed_mps * math.sin(yaw)
                if self.send_position:
                    self.mav.global_position_int_send(
                        ms,
                        286024000,
                        -812001000,
                        0,
                        0,
                        int(vn * 100),
                        int(ve * 100),
                        0,
                        int(round(self.heading_deg * 100)) % 36000,
                    )
                self.mav.attitude_send(
                    ms, 0.0, 0.0, math.atan2(math.sin(yaw), math.cos(yaw)), 0.0, 0.0, 0.0
                )
                for send in self.extra:
                    send(self.mav, t)
            time.sleep(0.002)

    def _on_message(self, msg: Any, t: float) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        with self.lock:
            self.received.append((t, msg))
        if kind != "COMMAND_LONG" or not self.answer_commands:
            return
        result = mp.RESULT_ACCEPTED
        if msg.command == mp.CMD_DO_SET_MODE:
            if self.autopilot == "px4":
                main, sub = int(msg.param2), int(msg.param3)
                self.mode = mp.PX4_MODES.get(
                    (main, sub if main == mp.PX4_MAIN_AUTO else 0), self.mode
                )
            else:
                self.mode = mp.ROVER_MODES.get(int(msg.param2), self.mode)
            if self.mode not in ("HOLD", "LOITER") and self._switches_left > 0 and self.armed:
                self._switches_left -= 1
                self._switch_at = t + 0.15
        elif (
            msg.command == mp.CMD_COMPONENT_ARM_DISARM
            and msg.param1 > 0.5
            and self.arm_refusals > 0
        ):
            self.arm_refusals -= 1
            self.arm_modes.append(self.mode)
            self.mav.statustext_send(2, b"Arm: Gyros inconsistent")
            result = mp.RESULT_FAILED
        elif msg.command == mp.CMD_COMPONENT_ARM_DISARM:
            if msg.param1 > 0.5:
                self.arm_modes.append(self.mode)
            self.armed = msg.param1 > 0.5
            if self.armed and self.mode_after_arm:
                self._switch_at = t + 0.05  # the RC switch's reading lands just after arming
                self._switches_left = self.mode_switch_repeats
        self.mav.command_ack_send(msg.command, result)
