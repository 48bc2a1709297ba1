"""The ``openconvoy`` commands of vehicles: ``vehicle --sim``, ``deploy``, ``abort`` (their work is in
``simvehicle`` and ``deploy``, imported when a command runs).
"""

from __future__ import annotations

import argparse

from openconvoy.bridge.limits import MIN_RATE_HZ
from openconvoy.core.args import (
    DURATION,
    FRACTION,
    POLICY_ARG_HELP,
    SEED,
    TIMEOUT,
    Flags,
    add_command,
    lazy_handler,
)
from openconvoy.core.args import integer as _int
from openconvoy.core.args import number as _num

VEHICLE_FLAGS: Flags = (
    ("--sim", dict(action="store_true", help="simulated vehicle (required)")),
    ("--id", dict(type=_int(1, 254), required=True, help="MAVLink system id (1..254)")),
    ("--mavlink", dict(required=True, metavar="URL", help="e.g. udpin:127.0.0.1:14551")),
    ("--autopilot", dict(choices=("ardupilot", "px4"), default="ardupilot")),
    (
        "--preset",
        dict(
            default=None,
            help="move like this vehicle preset (name or .toml) instead of the recorded "
            "firmware's loops and vehicle model (the default)",
        ),
    ),
    (
        "--timing",
        dict(
            choices=("short", "firmware"),
            default="short",
            help="boot/arming timeline: short (armable after --ready-after) or the "
            "recorded firmware's (ArduPilot GUIDED ~42 s, PX4 ~3.7 s)",
        ),
    ),
    (
        "--no-rc-switch",
        dict(
            action="store_true",
            help="ArduPilot: no RC mode switch reading (MANUAL) 0.42 s after boot",
        ),
    ),
    (
        "--speedup",
        dict(
            type=_num(0.0, 1000.0, lo_open=True),
            default=1.0,
            metavar="X",
            help="run the vehicle's clock X times faster than real time (default 1)",
        ),
    ),
    (
        "--boot-on-connect",
        dict(
            action="store_true",
            help="boot when the first MAVLink message arrives (as SITL waiting for serial0)",
        ),
    ),
    ("--home", dict(default="52.0,4.37,0", metavar="LAT,LON,ALT")),
    (
        "--start",
        dict(
            default="0,0,0",
            metavar="X,Y,HEADING_DEG",
            help="ENU metres around home; heading degrees, 0 = east, counter-clockwise",
        ),
    ),
    (
        "--ready-after",
        dict(
            type=_num(0.0, 3600.0),
            default=5.0,
            metavar="S",
            help="seconds until arming is possible (default 5)",
        ),
    ),
    (
        "--setpoint-timeout",
        dict(
            type=_num(0.0, 600.0, lo_open=True),
            default=3.0,
            metavar="S",
            help="ArduPilot GUIDED stops after this long without setpoints (default 3)",
        ),
    ),
    (
        "--max-rate",
        dict(
            type=_num(0.0, 1000.0, lo_open=True),
            default=None,
            metavar="HZ",
            help="refuse telemetry rates above HZ (default: the firmware's rule, ArduPilot < 50 Hz)",
        ),
    ),
    (
        "--gps-noise",
        dict(type=_num(0.0, 1000.0), default=0.0, metavar="M", help="position noise std"),
    ),
    ("--seed", dict(type=SEED, default=0)),
    (
        "--hold-drift",
        dict(
            type=_num(0.0, 10.0),
            default=0.0,
            metavar="MPS",
            help="PX4: position estimate drift while in Hold, m/s (Hold then drives around "
            "its hold point, as the firmware did); default 0",
        ),
    ),
    (
        "--other-streams",
        dict(
            type=_num(0.0, 5000.0),
            default=0.0,
            metavar="HZ",
            help="messages/s of the firmware's other streams (a real PX4 sends ~200/s)",
        ),
    ),
)
"""``openconvoy vehicle``'s flags."""

DEPLOY_FLAGS: Flags = (
    (
        "--policy",
        dict(
            required=True, help="preset name, policy .toml, module:Name, file.py:Name, .zip or .npz"
        ),
    ),
    (
        "--policy-arg",
        dict(action="append", metavar="KEY=VALUE", default=None, help=POLICY_ARG_HELP),
    ),
    ("--vehicle-id", dict(type=_int(0, 254), required=True, help="convoy index, 0 = leader")),
    ("--convoy", dict(required=True, metavar="CONVOY.toml", help="the convoy config")),
    (
        "--mavlink",
        dict(
            metavar="URL",
            help="autopilot link: /dev/ttyX (with --baud), udp:, udpin:, udpout:, tcp: "
            "(required with --link mavlink)",
        ),
    ),
    (
        "--link",
        dict(
            choices=("mavlink", "mavros", "px4-dds", "ap-dds"),
            default=None,
            help="how to reach the autopilot: MAVLink, MAVROS, PX4's DDS topics "
            "(px4-dds), or ArduPilot's AP_DDS ROS 2 topics (ap-dds; Cyclone DDS, or rclpy "
            "with --ap-dds-via rclpy; docs/ros.md); default: the convoy file's [[vehicle]] "
            "link, else mavlink",
        ),
    ),
    (
        "--ap-ns",
        dict(
            default="/ap",
            metavar="NS",
            help="--link ap-dds: AP_DDS's namespace (topics NS/navsat, NS/cmd_vel...; default /ap)",
        ),
    ),
    (
        "--px4-ns",
        dict(
            default="",
            metavar="NS",
            help="--link px4-dds: PX4's UXRCE_DDS_NS (topics rt/NS/fmu/...; default none)",
        ),
    ),
    (
        "--ap-dds-via",
        dict(
            choices=("cyclone", "rclpy"),
            default="cyclone",
            help="--link ap-dds: Cyclone DDS directly (default; no ROS install) or rclpy "
            "(make ros2's environment)",
        ),
    ),
    (
        "--dds-iface",
        dict(
            metavar="IFACE",
            help="--link px4-dds, ap-dds via Cyclone: keep DDS on this interface (default: "
            "Cyclone's configuration, CYCLONEDDS_URI)",
        ),
    ),
    (
        "--dds-domain",
        dict(
            type=_int(0, 232), default=0, help="--link px4-dds, ap-dds via Cyclone: DDS domain id"
        ),
    ),
    (
        "--dds-localhost",
        dict(action="store_true", help="--link px4-dds: DDS on loopback only, no multicast"),
    ),
    (
        "--ros",
        dict(
            type=int,
            choices=(1, 2),
            default=1,
            help="ROS version of --link mavros: 1 (rospy, ROS_MASTER_URI) or 2 (rclpy from "
            "make ros2's environment, OPENCONVOY_ROS2_VENV)",
        ),
    ),
    (
        "--mavros-ns",
        dict(default="/mavros", metavar="NS", help="MAVROS's namespace (default /mavros)"),
    ),
    (
        "--autopilot",
        dict(
            choices=("ardupilot", "px4"),
            default=None,
            help="the firmware behind MAVROS (default: told by its mode name)",
        ),
    ),
    ("--iface", dict(required=True, help="network interface for V2V (multicast, or DDS)")),
    (
        "--v2v",
        dict(
            choices=("multicast", "ros2"),
            default=None,
            help="what carries V2V: IPv6 multicast, or a ROS 2 topic over DDS (Cyclone, "
            "no ROS install; docs/ros.md); default the convoy file's [v2v] transport",
        ),
    ),
    ("--per", dict(type=FRACTION, default=0.0, help="emulated packet error rate 0..1")),
    (
        "--drop-at",
        dict(
            choices=("receiver", "sender"),
            default="receiver",
            help="where the emulated loss drops messages (default receiver)",
        ),
    ),
    ("--log", dict(metavar="DIR", help="write DIR/vehicle_N.csv and DIR/vehicle_N.json")),
    (
        "--bag",
        dict(
            action="store_true",
            help="also record DIR/vehicle_N_bag, a ROS 2 bag (MCAP) with the V2V bytes",
        ),
    ),
    (
        "--rate",
        dict(
            type=_num(MIN_RATE_HZ, 100.0),
            metavar="HZ",
            help=f"control rate, {MIN_RATE_HZ:g}..100 Hz (default: the policy's)",
        ),
    ),
    ("--dry-run", dict(action="store_true", help="everything but arming and setpoints")),
    (
        "--stay-armed",
        dict(
            action="store_true",
            help="leave the vehicle armed in HOLD at the end (default: at rest, disarmed)",
        ),
    ),
    (
        "--passive",
        dict(action="store_true", help="leader driven by a person: broadcast and log only"),
    ),
    ("--track", dict(metavar="FILE", help="leader follows this OpenConvoy JSON track")),
    (
        "--duration",
        dict(
            type=DURATION,
            metavar="S",
            help="end after S seconds of driving (default: the leader's scenario)",
        ),
    ),
    ("--baud", dict(type=_int(50, 20_000_000), default=57600, help="serial baud rate")),
    ("--seed", dict(type=SEED, default=0, help="seeds the emulated loss")),
    ("--arm-timeout", dict(type=TIMEOUT, default=60.0, metavar="S")),
    ("--connect-timeout", dict(type=TIMEOUT, default=30.0, metavar="S")),
    ("--quiet", dict(action="store_true", help="no status lines")),
)
"""``openconvoy deploy``'s flags."""

ABORT_FLAGS: Flags = (
    ("--iface", dict(required=True, help="network interface of the convoy's V2V")),
    ("--convoy", dict(metavar="CONVOY.toml", help="take group/port/compat from it")),
    ("--compat", dict(action="store_true", help="also on the IPv4 compatibility group")),
    ("--repeat", dict(type=_int(1, 1000), default=3, help="send this many times (default 3)")),
    (
        "--key",
        dict(
            metavar="KEY",
            help="sign the abort with this private key (its .cert beside it), e.g. "
            "NAME.keys/authority.key; required when the convoy has keys",
        ),
    ),
)
"""``openconvoy abort``'s flags."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's commands to ``openconvoy``'s subparsers (handlers import lazily)."""
    add_command(
        sub,
        "vehicle",
        VEHICLE_FLAGS,
        lazy_handler("openconvoy.bridge.simvehicle.vehicle", "run_vehicle_cli"),
        help="run a simulated MAVLink vehicle (ArduPilot Rover or PX4)",
        description="A simulated vehicle speaking MAVLink like ArduPilot Rover (GUIDED) or PX4 "
        "(OFFBOARD), driven by the simulator's plant. SIGUSR1: a person switches to MANUAL; "
        "SIGUSR2: toggle a telemetry freeze; SIGTERM/SIGINT: exit.",
    )
    add_command(
        sub,
        "deploy",
        DEPLOY_FLAGS,
        lazy_handler("openconvoy.bridge.deploy", "deploy_from_namespace"),
        help="drive a vehicle with a policy over MAVLink, talking V2V over IPv6 multicast",
        description="The real-time loop on a vehicle: telemetry -> convoy member -> policy -> "
        "setpoints, with BSMs over IPv6 multicast, failsafes and a safety envelope. "
        "SIGINT/SIGTERM: brake to rest (logged and broadcast), HOLD, disarm (unless "
        "--stay-armed), save the log, exit 0.",
    )
    add_command(
        sub,
        "abort",
        ABORT_FLAGS,
        lazy_handler("openconvoy.bridge.deploy", "abort_from_namespace"),
        help="broadcast a convoy-wide stop that every deploy obeys",
    )
