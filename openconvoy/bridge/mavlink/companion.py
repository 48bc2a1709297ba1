"""The MAVLink side of a companion-computer stand-in (MAVROS's ``mavconn``, an XRCE-DDS
agent's host): one pymavlink connection to the autopilot, sends serialised, and a receive
loop that hands each message to its handler by type.

The MAVROS, AP_DDS and PX4 DDS stand-ins (``bridge.ros.mavros_standin``,
``bridge.px4dds.standin``) forward their ROS/DDS side through one of these, so the loop that
reads the simulated autopilot is written once.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4


class CompanionMavlink:
    """A pymavlink connection at ``url`` (e.g. ``udpout:127.0.0.1:14551``) as system 1,
    component ``component_id`` (MAVROS: 240, MAV_COMP_ID_UDP_BRIDGE; an XRCE agent host:
    191, MAV_COMP_ID_ONBOARD_COMPUTER)."""

    def __init__(self, url: str, component_id: int) -> None:
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(
            url, source_system=1, source_component=component_id, dialect="ardupilotmega"
        )
        self._send_lock = threading.Lock()

    def send(self, fn: str, *args: Any) -> None:
        """Call pymavlink's ``mav.<fn>(*args)`` (e.g. ``"set_mode_send"``), one sender at a
        time; a socket error drops the message (UDP: the autopilot may not be up yet)."""
        with self._send_lock:
            try:
                getattr(self.conn.mav, fn)(*args)
            except OSError:
                pass

    def heartbeat(self) -> None:
        """The companion's own HEARTBEAT (onboard controller, no autopilot, active): the
        ground-station heartbeat the simulated autopilots watch for."""
        self.send(
            "heartbeat_send", MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0,
            MAV_STATE_ACTIVE,
        )  # fmt: skip

    def receive_loop(
        self,
        stop: threading.Event,
        handlers: Mapping[str, Callable[[Any], None]],
        timeout_s: float = 0.1,
    ) -> None:
        """Until ``stop`` is set: read each message and call ``handlers[its type]`` (types
        without a handler are skipped); waits at most ``timeout_s`` (s) per read, and 50 ms
        after a socket error (the autopilot not up yet)."""
        while not stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=timeout_s)
            except OSError:
                time.sleep(0.05)
                continue
            if msg is None:
                continue
            handler = handlers.get(msg.get_type())
            if handler is not None:
                handler(msg)

    def close(self) -> None:
        self.conn.close()


def run_threads(owner: str, *targets: Callable[[], None]) -> list[threading.Thread]:
    """Start each target in a daemon thread named ``owner`` + its name; the threads."""
    threads = []
    for fn in targets:
        th = threading.Thread(target=fn, daemon=True, name=f"{owner} {fn.__name__}")
        th.start()
        threads.append(th)
    return threads


def stop_threads(stop: threading.Event, threads: list[threading.Thread]) -> None:
    """Set ``stop`` and wait up to 2 s for each of ``threads`` (emptied)."""
    stop.set()
    for th in threads:
        th.join(2.0)
    threads.clear()
