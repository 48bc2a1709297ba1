"""A stand-in for PX4's DDS side (the uXRCE-DDS client plus its agent), in front of the
simulated PX4 over real MAVLink.

PX4 runs no DDS in our CI, so tests and the ``px4-dds`` demo run this in its place. It
offers the topics of PX4 main's ``src/modules/uxrce_dds_client/dds_topics.yaml`` that the
link uses, with ``utilities.hpp``'s names and QoS (``dds.py``) and px4_msgs' types
(``msgs.py``), and turns them into what the simulated firmware (``bridge.simvehicle.px4``,
PX4 main 752ecd3d1b as recorded) understands, so its offboard-loss failsafe and Hold stay
the firmware's:

- ``/fmu/in/offboard_control_mode`` is PX4's offboard signal (commander's
  ``offboard_control_mode`` timeout, COM_OF_LOSS_T): each one (with ``velocity`` or
  ``position`` set) forwards the latest ``/fmu/in/trajectory_setpoint`` as MAVLink
  SET_POSITION_TARGET_LOCAL_NED (frame LOCAL_NED, velocity + yaw). When the stream stops,
  nothing reaches the simulated PX4, whose own failsafe then fires after 1 s. A setpoint
  with no recent offboard_control_mode (``SIGNAL_S``) is held, not forwarded, as PX4 uses
  trajectory_setpoint only while the signal is alive.
- ``/fmu/in/vehicle_command``: COMPONENT_ARM_DISARM and DO_SET_MODE become COMMAND_LONG
  with the same parameters; the COMMAND_ACK comes back on ``/fmu/out/vehicle_command_ack``.
- ``/fmu/out/vehicle_status`` on every HEARTBEAT (arming_state from base_mode's SAFETY_ARMED
  bit, nav_state from the custom mode as commander's ``get_nav_state``/MAVLink's
  ``px4_custom_mode`` map, ``failsafe`` while the autopilot's "Failsafe activated" holds),
  ``/fmu/out/vehicle_global_position`` and ``/fmu/out/vehicle_local_position`` on every
  GLOBAL_POSITION_INT (NED from the first fix; heading = hdg, NED radians).

Not modelled: the other topics, timesync (timestamps are this machine's monotonic clock in
µs), the agent's session handling.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from typing import Any

from openconvoy.bridge.mavlink import protocol as mp
from openconvoy.bridge.mavlink.companion import CompanionMavlink, run_threads, stop_threads
from openconvoy.bridge.px4dds import msgs
from openconvoy.bridge.px4dds.dds import IN_QOS, OUT_QOS, Participant, take_all, topic_name

SIGNAL_S = 0.5
"""A trajectory_setpoint is forwarded only within this long (s) after an offboard_control_mode."""

NAV_STATES: dict[str, int] = {
    "MANUAL": msgs.NAVIGATION_STATE_MANUAL,
    "POSCTL": msgs.NAVIGATION_STATE_POSCTL,
    "LOITER": msgs.NAVIGATION_STATE_AUTO_LOITER,
    "OFFBOARD": msgs.NAVIGATION_STATE_OFFBOARD,
}
"""Our MAVLink mode names -> VehicleStatus nav_state."""

TYPE_MASK_VEL_YAW = 0b100111000111
"""SET_POSITION_TARGET type_mask: velocity and yaw used (position, acceleration, yaw rate
ignored)."""


def now_us() -> int:
    """PX4-style timestamp: monotonic microseconds."""
    return int(time.monotonic() * 1e6)


class Px4DdsStandIn:
    """PX4's DDS side under namespace ``ns`` on DDS ``domain_id``, forwarding to the
    simulated PX4 at ``mavlink_url`` (pymavlink URL, e.g. ``udpout:127.0.0.1:14551``).
    ``start`` begins; ``stop`` ends (idempotent). ``dropped`` counts bad DDS input."""

    def __init__(
        self,
        mavlink_url: str,
        ns: str = "",
        domain_id: int = 0,
        localhost: bool = True,
        iface: str | None = None,
    ) -> None:
        self.ns = ns
        # 191: MAV_COMP_ID_ONBOARD_COMPUTER, as an XRCE agent host would be
        self.mavlink = CompanionMavlink(mavlink_url, 191)
        self.part = Participant(domain_id, localhost and not iface, iface)
        p, n = self.part, ns
        self.r_ocm = p.reader(topic_name(n, "in", msgs.OffboardControlMode), msgs.OffboardControlMode, IN_QOS)  # fmt: skip
        self.r_sp = p.reader(topic_name(n, "in", msgs.TrajectorySetpoint), msgs.TrajectorySetpoint, IN_QOS)  # fmt: skip
        self.r_cmd = p.reader(topic_name(n, "in", msgs.VehicleCommand), msgs.VehicleCommand, IN_QOS)
        self.w_status = p.writer(topic_name(n, "out", msgs.VehicleStatus), msgs.VehicleStatus, OUT_QOS)  # fmt: skip
        self.w_gpos = p.writer(topic_name(n, "out", msgs.VehicleGlobalPosition), msgs.VehicleGlobalPosition, OUT_QOS)  # fmt: skip
        self.w_lpos = p.writer(topic_name(n, "out", msgs.VehicleLocalPosition), msgs.VehicleLocalPosition, OUT_QOS)  # fmt: skip
        self.w_ack = p.writer(topic_name(n, "out", msgs.VehicleCommandAck), msgs.VehicleCommandAck, OUT_QOS)  # fmt: skip
        self.dropped: dict[str, int] = {}
        self.setpoints_forwarded = 0
        self.tgt_system = 0
        self.failsafe = False
        self.ref: tuple[float, float] | None = None
        self._t_gpos = -math.inf
        self._gpos_gap = math.inf  # s between the last two GLOBAL_POSITION_INT
        self._sp: msgs.TrajectorySetpoint | None = None
        self._t_signal = -math.inf
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> Px4DdsStandIn:
        """Start the MAVLink and DDS threads."""
        self._threads = run_threads("px4-dds stand-in", self._mavlink_loop, self._dds_loop)
        return self

    def stop(self) -> None:
        """Stop the threads, close MAVLink and the DDS participant (idempotent)."""
        stop_threads(self._stop, self._threads)
        self.mavlink.close()
        self.part.close()

    # ------------------------------------------------------------------ DDS in

    def _dds_loop(self) -> None:
        """Take the /fmu/in samples as they arrive (a Cyclone wait set, no polling); the
        GCS heartbeat the simulated PX4 expects, once a second."""
        waiter = self.part.waiter([self.r_sp, self.r_ocm, self.r_cmd])
        hb = 0.0
        while not self._stop.is_set():
            waiter.wait(0.1)
            self._handle("trajectory_setpoint", msgs.TrajectorySetpoint, self._on_setpoint)
            self._handle(
                "offboard_control_mode", msgs.OffboardControlMode, self._on_offboard_control_mode
            )
            self._handle("vehicle_command", msgs.VehicleCommand, self._on_command)
            if time.monotonic() - hb > 1.0:
                hb = time.monotonic()
                self.mavlink.heartbeat()

    def _handle(self, key: str, data_type: type, handler: Any) -> None:
        """Every pending sample of topic ``key`` to ``handler``; one it cannot take (a
        command number MAVLink cannot carry, ...) is bad input: counted, dropped."""
        reader = {"trajectory_setpoint": self.r_sp, "offboard_control_mode": self.r_ocm}.get(
            key, self.r_cmd
        )
        for sample in take_all(reader, self.dropped, key, data_type):
            try:
                handler(sample)
            except (ValueError, OverflowError, TypeError, struct.error):
                self.dropped[key] = self.dropped.get(key, 0) + 1

    def _on_setpoint(self, sp: msgs.TrajectorySetpoint) -> None:
        """Keep the newest setpoint; forward it at once while the offboard signal lives."""
        vel = list(sp.velocity)
        if not all(math.isfinite(v) for v in vel[:2]):
            self.dropped["trajectory_setpoint"] = self.dropped.get("trajectory_setpoint", 0) + 1
            return  # only velocity control is modelled: no velocity, nothing to follow
        self._sp = sp
        if time.monotonic() - self._t_signal < SIGNAL_S:
            self._forward(sp)

    def _on_offboard_control_mode(self, ocm: msgs.OffboardControlMode) -> None:
        """The offboard signal: forward the held setpoint (PX4 keeps following it)."""
        if not (ocm.velocity or ocm.position):
            return
        self._t_signal = time.monotonic()
        if self._sp is not None:
            self._forward(self._sp)

    def _forward(self, sp: msgs.TrajectorySetpoint) -> None:
        vn, ve = float(sp.velocity[0]), float(sp.velocity[1])
        vd = float(sp.velocity[2]) if math.isfinite(sp.velocity[2]) else 0.0
        yaw = float(sp.yaw) if math.isfinite(sp.yaw) else 0.0
        self.mavlink.send(
            "set_position_target_local_ned_send",
            int(time.monotonic() * 1000) & 0xFFFFFFFF, self.tgt_system, 1, mp.MAV_FRAME_LOCAL_NED,
            TYPE_MASK_VEL_YAW, 0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, yaw, 0.0,
        )  # fmt: skip
        self.setpoints_forwarded += 1

    def _on_command(self, cmd: msgs.VehicleCommand) -> None:
        if cmd.command not in (msgs.VEHICLE_CMD_COMPONENT_ARM_DISARM, msgs.VEHICLE_CMD_DO_SET_MODE):
            self._ack(cmd.command, msgs.VEHICLE_CMD_RESULT_DENIED)  # not modelled here
            return
        if cmd.command == msgs.VEHICLE_CMD_DO_SET_MODE:
            self.failsafe = False  # a mode asked for ends the failsafe (user took over)
        self.mavlink.send(
            "command_long_send",
            self.tgt_system, 1, cmd.command, 0, cmd.param1, cmd.param2, cmd.param3,
            cmd.param4, float(cmd.param5), float(cmd.param6), cmd.param7,
        )  # fmt: skip

    def _ack(self, command: int, result: int) -> None:
        self.w_ack.write(msgs.VehicleCommandAck(timestamp=now_us(), command=command, result=result))

    # ------------------------------------------------------------------ MAVLink

    def _mavlink_loop(self) -> None:
        self.mavlink.receive_loop(
            self._stop,
            {
                "HEARTBEAT": self._on_heartbeat,
                "GLOBAL_POSITION_INT": self._on_global_position,
                "COMMAND_ACK": lambda m: self._ack(int(m.command), int(m.result)),
                "STATUSTEXT": self._on_statustext,
            },
        )

    def _on_statustext(self, msg: Any) -> None:
        if "Failsafe activated" in str(msg.text):
            self.failsafe = True

    def _on_heartbeat(self, hb: Any) -> None:
        if hb.type == mp.MAV_TYPE_GCS or hb.autopilot == 8:
            return  # a ground station or companion, not the vehicle
        self.tgt_system = hb.get_srcSystem()
        if self._gpos_gap > 0.05:  # GLOBAL_POSITION_INT at 50 Hz (dds_topics.yaml's rate_limit),
            # asked again at each heartbeat until it comes so: a booting PX4 drops the request
            self.mavlink.send(
                "command_long_send",
                self.tgt_system, 1, mp.CMD_SET_MESSAGE_INTERVAL, 0,
                mp.MSG_GLOBAL_POSITION_INT, 20000, 0, 0, 0, 0, 0,
            )  # fmt: skip
        main, sub = mp.px4_mode_parts(int(hb.custom_mode))
        name = mp.PX4_MODES.get((main, sub)) or mp.PX4_MODES.get((main, 0), "")
        nav = NAV_STATES.get(name, msgs.NAVIGATION_STATE_MANUAL)
        if nav == msgs.NAVIGATION_STATE_OFFBOARD:
            self.failsafe = False  # back in offboard by itself: the failsafe has ended
        armed = bool(hb.base_mode & 128)
        self.w_status.write(
            msgs.VehicleStatus(
                timestamp=now_us(),
                arming_state=msgs.ARMING_STATE_ARMED if armed else msgs.ARMING_STATE_DISARMED,
                nav_state=nav,
                nav_state_user_intention=nav,
                nav_state_display=nav,
                accepts_offboard_setpoints=nav == msgs.NAVIGATION_STATE_OFFBOARD,
                vehicle_type=msgs.VEHICLE_TYPE_ROVER,
                failsafe=self.failsafe,
                system_type=int(hb.type),
                system_id=self.tgt_system,
                component_id=1,
                pre_flight_checks_pass=True,
            )
        )

    def _on_global_position(self, g: Any) -> None:
        from openconvoy.comms.geodesy import Origin, geodetic_to_enu

        lat, lon, alt = g.lat / 1e7, g.lon / 1e7, g.alt / 1e3
        t = time.monotonic()
        self._gpos_gap, self._t_gpos = t - self._t_gpos, t
        ts = now_us()
        self.w_gpos.write(
            msgs.VehicleGlobalPosition(
                timestamp=ts, timestamp_sample=ts, lat=lat, lon=lon, alt=alt,
                lat_lon_valid=True, alt_valid=True,
            )
        )  # fmt: skip
        if self.ref is None:
            self.ref = (lat, lon)
        east, north, _ = geodetic_to_enu(Origin(self.ref[0], self.ref[1], 0.0), lat, lon, 0.0)
        heading = (
            math.nan if g.hdg == 65535 else math.remainder(math.radians(g.hdg / 100), math.tau)
        )
        self.w_lpos.write(
            msgs.VehicleLocalPosition(
                timestamp=ts, timestamp_sample=ts, xy_valid=True, z_valid=True,
                v_xy_valid=True, v_z_valid=True, x=float(north), y=float(east),
                z=-g.relative_alt / 1e3, vx=g.vx / 100, vy=g.vy / 100, vz=g.vz / 100,
                heading=heading, heading_good_for_control=math.isfinite(heading),
                xy_global=True, z_global=True, ref_timestamp=ts, ref_lat=self.ref[0],
                ref_lon=self.ref[1],
            )
        )  # fmt: skip
