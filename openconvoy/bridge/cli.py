"""The ``openconvoy`` commands of vehicles: ``vehicle --sim``, ``deploy``, ``abort`` (their work is in
``simvehicle`` and ``deploy``, imported when a command runs).
"""

from __future__ import annotations

import argparse

from openconvoy.core.args import DURATION, FRACTION, RATE_HZ, SEED, TIMEOUT
from openconvoy.core.args import integer as _int
from openconvoy.core.args import number as _num


def _add_bridge(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "vehicle",
        help="run a simulated MAVLink vehicle (ArduPilot Rover or PX4)",
        description="A simulated vehicle speaking MAVLink like ArduPilot Rover (GUIDED) or PX4 "
        "(OFFBOARD), driven by the simulator's plant. SIGUSR1: a person switches to MANUAL; "
        "SIGUSR2: toggle a telemetry freeze; SIGTERM/SIGINT: exit.",
    )
    p.add_argument("--sim", action="store_true", help="simulated vehicle (required)")
    p.add_argument("--id", type=_int(1, 254), required=True, help="MAVLink system id (1..254)")
    p.add_argument("--mavlink", required=True, metavar="URL", help="e.g. udpin:127.0.0.1:14551")
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot")
    p.add_argument(
        "--preset",
        default=None,
        help="move like this vehicle preset (name or .toml) instead of the recorded "
        "firmware's loops and vehicle model (the default)",
    )
    p.add_argument(
        "--timing",
        choices=("short", "firmware"),
        default="short",
        help="boot/arming timeline: short (armable after --ready-after) or the "
        "recorded firmware's (ArduPilot GUIDED ~42 s, PX4 ~3.7 s)",
    )
    p.add_argument(
        "--no-rc-switch",
        action="store_true",
        help="ArduPilot: no RC mode switch reading (MANUAL) 0.42 s after boot",
    )
    p.add_argument(
        "--speedup",
        type=_num(0.0, 1000.0, lo_open=True),
        default=1.0,
        metavar="X",
        help="run the vehicle's clock X times faster than real time (default 1)",
    )
    p.add_argument(
        "--boot-on-connect",
        action="store_true",
        help="boot when the first MAVLink message arrives (as SITL waiting for serial0)",
    )
    p.add_argument("--home", default="52.0,4.37,0", metavar="LAT,LON,ALT")
    p.add_argument(
        "--start",
        default="0,0,0",
        metavar="X,Y,HEADING_DEG",
        help="ENU metres around home; heading degrees, 0 = east, counter-clockwise",
    )
    p.add_argument(
        "--ready-after",
        type=_num(0.0, 3600.0),
        default=5.0,
        metavar="S",
        help="seconds until arming is possible (default 5)",
    )
    p.add_argument(
        "--setpoint-timeout",
        type=_num(0.0, 600.0, lo_open=True),
        default=3.0,
        metavar="S",
        help="ArduPilot GUIDED stops after this long without setpoints (default 3)",
    )
    p.add_argument(
        "--max-rate",
        type=_num(0.0, 1000.0, lo_open=True),
        default=None,
        metavar="HZ",
        help="refuse telemetry rates above HZ (default: the firmware's rule, ArduPilot < 50 Hz)",
    )
    p.add_argument(
        "--gps-noise", type=_num(0.0, 1000.0), default=0.0, metavar="M", help="position noise std"
    )
    p.add_argument("--seed", type=SEED, default=0)

    def _vehicle(args: argparse.Namespace) -> int:
        from openconvoy.bridge.simvehicle import run_vehicle_cli

        return run_vehicle_cli(args)

    p.set_defaults(handler=_vehicle)
    _add_deploy_commands(sub)


def _add_deploy_commands(sub: argparse._SubParsersAction) -> None:
    """``deploy``, ``abort`` (bridge.deploy)."""
    p = sub.add_parser(
        "deploy",
        help="drive a vehicle with a policy over MAVLink, talking V2V over IPv6 multicast",
        description="The real-time loop on a vehicle: telemetry -> convoy member -> policy -> "
        "setpoints, with BSMs over IPv6 multicast, failsafes and a safety envelope. "
        "SIGINT/SIGTERM: stop, HOLD, save the log, exit 0.",
    )
    p.add_argument("--policy", required=True, help="preset name, policy .toml, .zip or .npz")
    p.add_argument(
        "--vehicle-id", type=_int(0, 254), required=True, help="convoy index, 0 = leader"
    )
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml", help="the convoy config")
    p.add_argument(
        "--mavlink",
        required=True,
        metavar="URL",
        help="autopilot link: /dev/ttyX (with --baud), udp:, udpin:, udpout:, tcp:",
    )
    p.add_argument("--iface", required=True, help="network interface for V2V multicast")
    p.add_argument("--per", type=FRACTION, default=0.0, help="emulated packet error rate 0..1")
    p.add_argument(
        "--drop-at",
        choices=("receiver", "sender"),
        default="receiver",
        help="where the emulated loss drops messages (default receiver)",
    )
    p.add_argument("--log", metavar="DIR", help="write DIR/vehicle_N.csv and DIR/vehicle_N.json")
    p.add_argument(
        "--rate", type=RATE_HZ, metavar="HZ", help="control rate (default: the policy's)"
    )
    p.add_argument("--dry-run", action="store_true", help="everything but arming and setpoints")
    p.add_argument(
        "--passive", action="store_true", help="leader driven by a person: broadcast and log only"
    )
    p.add_argument("--track", metavar="FILE", help="leader follows this OpenConvoy JSON track")
    p.add_argument(
        "--duration",
        type=DURATION,
        metavar="S",
        help="end after S seconds of driving (default: the leader's scenario)",
    )
    p.add_argument("--baud", type=_int(50, 20_000_000), default=57600, help="serial baud rate")
    p.add_argument("--seed", type=SEED, default=0, help="seeds the emulated loss")
    p.add_argument("--arm-timeout", type=TIMEOUT, default=60.0, metavar="S")
    p.add_argument("--connect-timeout", type=TIMEOUT, default=30.0, metavar="S")
    p.add_argument("--quiet", action="store_true", help="no status lines")

    def _deploy(args: argparse.Namespace) -> int:
        from openconvoy.bridge.deploy import deploy_from_namespace

        return deploy_from_namespace(args)

    p.set_defaults(handler=_deploy)

    p = sub.add_parser("abort", help="broadcast a convoy-wide stop that every deploy obeys")
    p.add_argument("--iface", required=True, help="network interface of the convoy's V2V")
    p.add_argument("--convoy", metavar="CONVOY.toml", help="take group/port/compat from it")
    p.add_argument("--compat", action="store_true", help="also on the IPv4 compatibility group")
    p.add_argument(
        "--repeat", type=_int(1, 1000), default=3, help="send this many times (default 3)"
    )
    p.add_argument(
        "--key",
        metavar="KEY",
        help="sign the abort with this private key (its .cert beside it), e.g. "
        "NAME.keys/authority.key; required when the convoy has keys",
    )

    def _abort(args: argparse.Namespace) -> int:
        from openconvoy.bridge.deploy import abort_from_namespace

        return abort_from_namespace(args)

    p.set_defaults(handler=_abort)


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's commands to ``openconvoy``'s subparsers (handlers import lazily)."""
    _add_bridge(sub)
