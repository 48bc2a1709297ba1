"""The ``openconvoy`` commands of the V2V layer: ``bsm listen | send | decode`` and ``keys init |
issue`` (their work is in ``tools`` and ``security.keystore``, imported when a command runs).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from openconvoy.core.args import TIMEOUT, Flags, add_command
from openconvoy.core.args import integer as _int
from openconvoy.core.args import number as _num
from openconvoy.core.errors import ConfigError

# comms.multicast.DEFAULT_GROUP / DEFAULT_PORT and comms.dds.DEFAULT_TOPIC / DEFAULT_DOMAIN,
# spelled out to keep imports lazy (tests/comms/test_cli.py and test_bsm_dds.py check they agree).
DEFAULT_GROUP, DEFAULT_PORT = "ff15::4f43", 4200
DEFAULT_ROS2_TOPIC, DEFAULT_ROS2_DOMAIN = "/openconvoy/v2v", 0
TRANSPORTS = ("multicast", "ros2")
"""``--transport``: as the convoy file's ``[v2v] transport`` (and ``deploy --v2v``)."""


class _Given(argparse.Action):
    """Stores a flag's value and notes the flag as given (``args.given``), so that a flag
    of the other transport is refused rather than silently ignored."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None):
        setattr(namespace, self.dest, values)
        namespace.given = getattr(namespace, "given", frozenset()) | {option_string}


def _add_bsm(sub: argparse._SubParsersAction) -> None:
    """``bsm listen | send | decode`` (the work is in ``openconvoy.comms.tools``)."""
    bsm = sub.add_parser(
        "bsm",
        help="J2735 BSM field tools: listen, send, decode",
        description="Field tools for the V2V layer: J2735 Basic Safety Messages (UPER "
        "MessageFrames) over IPv6 multicast or a ROS 2 topic (DDS), and the original "
        "implementation's JSON.",
    )
    cmds = bsm.add_subparsers(dest="bsm_command", metavar="SUBCOMMAND", required=True)
    for add in (_add_listen, _add_send, _add_decode):
        add(cmds)


NET_FLAGS: Flags = (
    ("--iface", dict(required=True, help="network interface, e.g. wlan0 (multicast, or DDS)")),
    (
        "--transport",
        dict(
            choices=TRANSPORTS,
            default=None,
            help="IPv6 multicast, or the ROS 2 topic over DDS (Cyclone, no ROS install) of a "
            'convoy with [v2v] transport = "ros2"; default the --convoy file\'s [v2v] '
            "transport, else multicast",
        ),
    ),
    (
        "--group",
        dict(
            action=_Given,
            default=DEFAULT_GROUP,
            help=f"IPv6 multicast group (default the --convoy file's, else {DEFAULT_GROUP})",
        ),
    ),
    (
        "--port",
        dict(
            action=_Given,
            type=_int(1, 65535),
            default=DEFAULT_PORT,
            help=f"UDP port (default the --convoy file's, else {DEFAULT_PORT})",
        ),
    ),
    (
        "--ros2-topic",
        dict(
            metavar="TOPIC",
            help="--transport ros2: the ROS 2 topic (default the --convoy file's [v2v] "
            f"ros2_topic, else {DEFAULT_ROS2_TOPIC})",
        ),
    ),
    (
        "--ros2-domain",
        dict(
            type=_int(0, 232),
            metavar="N",
            help="--transport ros2: the DDS domain id (default the --convoy file's [v2v] "
            f"ros2_domain, else {DEFAULT_ROS2_DOMAIN})",
        ),
    ),
)
"""``--iface``, ``--transport`` and the transports' addresses, of the BSM tools."""

LISTEN_FLAGS: Flags = NET_FLAGS + (
    (
        "--compat",
        dict(
            action="store_true", help="also listen for the original JSON format on 224.0.0.1:5004"
        ),
    ),
    ("--count", dict(type=_int(1, 10**12), metavar="N", help="exit after N messages")),
    ("--timeout", dict(type=TIMEOUT, metavar="S", help="exit after S seconds")),
    (
        "--convoy",
        dict(
            metavar="CONVOY.toml",
            help="verify signed BSMs with this convoy's certificates (its keys directory); "
            "prints accepted/rejected per sender and a summary at exit; its [v2v] section "
            "gives the transport's defaults",
        ),
    ),
)
"""``bsm listen``'s flags."""

SEND_FLAGS: Flags = NET_FLAGS + (
    (
        "--hop-limit",
        dict(
            action=_Given,
            type=_int(1, 255),
            default=1,
            help="IPv6 hop limit (default the --convoy file's, else 1)",
        ),
    ),
    ("--count", dict(type=_int(0, 10**12), default=10, help="messages to send (default 10)")),
    (
        "--rate",
        dict(
            type=_num(0.0, 100_000.0, lo_open=True), default=10.0, metavar="HZ", help="default 10"
        ),
    ),
    ("--lat", dict(type=_num(-90.0, 90.0), default=28.6024, help="start latitude, degrees")),
    ("--lon", dict(type=_num(-180.0, 180.0), default=-81.2001, help="start longitude, degrees")),
    (
        "--elev",
        dict(type=_num(-1000.0, 10_000.0), default=0.0, help="elevation, metres (default 0)"),
    ),
    ("--speed", dict(type=_num(0.0, 163.8), default=0.0, help="m/s (default 0)")),
    (
        "--heading",
        dict(
            type=_num(0.0, 360.0, hi_open=True),
            default=0.0,
            help="compass degrees, 0 = north, clockwise (default 0)",
        ),
    ),
    ("--id", dict(metavar="HEX", help="temporary id, 8 hex digits")),
    (
        "--compat-car",
        dict(
            type=_int(0, 254),
            metavar="N",
            help="also send the original JSON format as convoy position N (IPv4)",
        ),
    ),
    (
        "--key",
        dict(
            metavar="KEY",
            help="sign as IEEE 1609.2 SPDUs with this key (its .cert beside it; a foreign "
            "convoy's key makes a forger that has a key)",
        ),
    ),
    (
        "--convoy",
        dict(
            metavar="CONVOY.toml",
            help="the authority for --key (default: the key's directory); its [v2v] section "
            "gives the transport's defaults",
        ),
    ),
    ("--frame", dict(metavar="HEX", help="replay this captured datagram COUNT times")),
)
"""``bsm send``'s flags."""

DECODE_FLAGS: Flags = (
    ("hex", dict(nargs="+", metavar="HEX", help="the frame, hex (spaces allowed)")),
    ("--json", dict(action="store_true", help="one JSON object instead of lines")),
)
"""``bsm decode``'s flags."""


MULTICAST_ONLY = ("--group", "--port", "--hop-limit", "--compat", "--compat-car")
"""Flags that mean nothing over ROS 2 (``_link`` refuses them there)."""


def _convoy_v2v(path: str | None) -> Any:
    """The ``[v2v]`` section of convoy file ``path`` (None without one)."""
    if not path:
        return None
    from openconvoy.convoy import load_convoy

    return load_convoy(path).v2v


def _given(args: argparse.Namespace) -> list[str]:
    """The multicast-only flags given on the command line, in ``MULTICAST_ONLY``'s order."""
    given = set(getattr(args, "given", ()))
    if getattr(args, "compat", False):
        given.add("--compat")
    if getattr(args, "compat_car", None) is not None:
        given.add("--compat-car")
    return [f for f in MULTICAST_ONLY if f in given]


def _link(args: argparse.Namespace, v2v: Any) -> dict[str, Any]:
    """The BSM tools' transport keywords: ``ros2`` = (topic, domain) or None, and for
    multicast ``group``, ``port`` (and ``send``'s ``hop_limit``). Each is the flag given,
    else the ``--convoy`` file's ``[v2v]`` (``v2v``), else the default; the transport is
    ``--transport``, else the file's. ``ConfigError`` for a flag of the other transport."""
    transport = args.transport or (v2v.transport if v2v is not None else "multicast")
    return _ros2_link(args, v2v) if transport == "ros2" else _multicast_link(args, v2v)


def _ros2_link(args: argparse.Namespace, v2v: Any) -> dict[str, Any]:
    """``_link`` over ROS 2: refuses every multicast-only flag given."""
    given = _given(args)
    if given:
        whence = "--transport ros2" if args.transport else 'the --convoy file\'s transport = "ros2"'
        raise ConfigError(f"{given[0]}: multicast only, not with {whence}")
    topic = args.ros2_topic or (v2v.ros2_topic if v2v is not None else DEFAULT_ROS2_TOPIC)
    domain = args.ros2_domain
    if domain is None:
        domain = v2v.ros2_domain if v2v is not None else DEFAULT_ROS2_DOMAIN
    return {"ros2": (topic, domain), "group": DEFAULT_GROUP, "port": DEFAULT_PORT}


def _multicast_link(args: argparse.Namespace, v2v: Any) -> dict[str, Any]:
    """``_link`` over IPv6 multicast: refuses ``--ros2-topic`` and ``--ros2-domain``."""
    for flag, value in (("--ros2-topic", args.ros2_topic), ("--ros2-domain", args.ros2_domain)):
        if value is not None:
            raise ConfigError(f"{flag}: only with --transport ros2, not over multicast")
    given = _given(args)
    link: dict[str, Any] = {"ros2": None}
    for key in ("group", "port", "hop_limit"):
        if hasattr(args, key):  # listen has no --hop-limit
            mine = v2v is None or "--" + key.replace("_", "-") in given
            link[key] = getattr(args, key) if mine else getattr(v2v, key)
    return link


def _where(link: dict[str, Any]) -> str:
    """Where ``send`` sent: ``[group]:port``, or the ROS 2 topic and DDS domain."""
    if link["ros2"] is not None:
        return "ROS 2 topic {} (DDS domain {})".format(*link["ros2"])
    return f"[{link['group']}]:{link['port']}"


def _add_listen(cmds: argparse._SubParsersAction) -> None:
    add_command(
        cmds,
        "listen",
        LISTEN_FLAGS,
        _listen,
        help="print BSMs heard on an interface, one line each",
        description="Prints every BSM heard (anyone's, not only a convoy's) on the multicast "
        "group or, with --transport ros2, the ROS 2 topic: temporary id, "
        "msgCnt, latitude and longitude (degrees), speed (m/s), heading (compass degrees), "
        "age (s, from secMark and this host's clock). Ctrl-C stops.",
    )


def _listen(args: argparse.Namespace) -> int:
    from openconvoy.comms import tools

    v2v = _convoy_v2v(args.convoy)
    link = _link(args, v2v)
    tools.listen(
        args.iface,
        **link,
        compat_enabled=args.compat,
        count=args.count,
        timeout_s=args.timeout,
        auth=_verifier(v2v),
    )
    return 0


def _add_send(cmds: argparse._SubParsersAction) -> None:
    add_command(
        cmds,
        "send",
        SEND_FLAGS,
        _send,
        help="send test BSMs",
        description="Sends COUNT BSMs at RATE Hz from a test vehicle starting at LAT, LON "
        "and moving at SPEED along HEADING (compass degrees: 0 = north, clockwise), to the "
        "multicast group or, with --transport ros2, on the ROS 2 topic (after up to 3 s of "
        "DDS discovery, and 0.5 s more).",
    )


def _signer(key: str | None, v2v: Any):
    """``bsm send --key``'s signer (None without a key); ``v2v``: the ``--convoy`` file's
    ``[v2v]`` (its keys directory the authority), or None."""
    if not key:
        return None
    import time

    from openconvoy.comms.security.auth import Authenticator
    from openconvoy.comms.security.keystore import signer_of_key

    keys = v2v.keys if v2v is not None else None
    return Authenticator(signer_of_key(key, keys, time.time()))


def _send(args: argparse.Namespace) -> int:
    from openconvoy.comms import tools

    v2v = _convoy_v2v(args.convoy)
    link = _link(args, v2v)
    auth = _signer(args.key, v2v)
    n = tools.send(
        args.iface,
        **link,
        count=args.count,
        rate_hz=args.rate,
        lat_deg=args.lat,
        lon_deg=args.lon,
        elev_m=args.elev,
        speed_mps=args.speed,
        heading_deg=args.heading,
        temp_id=tools.temp_id_arg(args.id) if args.id else tools.DEFAULT_SEND_ID,
        compat_car=args.compat_car,
        auth=auth,
        frame=tools.parse_hex(args.frame) if args.frame else None,
    )
    print(f"sent {n} BSMs on {args.iface} to {_where(link)}", file=sys.stderr)
    return 0


def _add_decode(cmds: argparse._SubParsersAction) -> None:
    add_command(
        cmds,
        "decode",
        DECODE_FLAGS,
        _decode,
        help="print one UPER MessageFrame's BSM core in physical units",
        description="Decodes a hex-encoded J2735 MessageFrame (messageId 20) and prints the "
        "core fields in physical units (latitude and longitude in degrees).",
    )


def _decode(args: argparse.Namespace) -> int:
    from openconvoy.comms import tools

    data = tools.parse_hex(" ".join(args.hex))
    tools.require_codec()
    try:
        lines = tools.decode_lines(data, as_json=args.json)
    except ValueError as exc:
        raise ConfigError(f"not a valid J2735 BSM frame: {exc}") from None
    print("\n".join(lines))
    return 0


def _verifier(v2v: Any):
    """``bsm listen --convoy``'s verifier: the convoy authority's certificate only (None
    without ``v2v``, the convoy file's ``[v2v]``)."""
    if v2v is None:
        return None
    from openconvoy.comms.security.auth import Authenticator, Credentials
    from openconvoy.comms.security.keystore import load_authority

    authority, _ = load_authority(v2v.keys)
    return Authenticator(Credentials(authority), window_s=v2v.replay_window_s)


def _add_keys(sub: argparse._SubParsersAction) -> None:
    """``keys init | issue`` (the work is in ``openconvoy.comms.security.keystore``)."""
    keys = sub.add_parser(
        "keys",
        help="the convoy's signing keys: authority and vehicle certificates",
        description="IEEE 1609.2 keys for signed BSMs and aborts. The keys live in NAME.keys/ "
        "beside the convoy file (or [v2v] keys). deploy signs and verifies every message and "
        'refuses to start without keys, unless the convoy file says auth = "off". See '
        "docs/security.md.",
    )
    cmds = keys.add_subparsers(dest="keys_command", metavar="SUBCOMMAND", required=True)
    p = cmds.add_parser("init", help="make the convoy authority's key and certificate")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml")
    p.add_argument("--force", action="store_true", help="replace an existing authority")
    p.set_defaults(handler=_keys_handler)
    p = cmds.add_parser("issue", help="issue a vehicle's key and certificate")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml")
    p.add_argument(
        "--vehicle-id", type=_int(0, 254), required=True, help="convoy index, 0 = leader"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the vehicle's existing key; its old certificate is revoked (listed in "
        "KEYS/revoked: copy that file to every vehicle)",
    )
    p.set_defaults(handler=_keys_handler)
    p = cmds.add_parser("operator", help="issue an operator's key (signs aborts only)")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml")
    p.add_argument("--name", required=True, help="the operator's name (letters, digits, - _)")
    p.add_argument(
        "--force", action="store_true", help="replace it; the old certificate is revoked"
    )
    p.set_defaults(handler=_keys_handler)


def _keys_handler(args: argparse.Namespace) -> int:
    import time

    from openconvoy.comms.security import keystore
    from openconvoy.convoy import load_convoy

    convoy = load_convoy(args.convoy)
    keys_dir = convoy.v2v.keys
    if args.keys_command == "init":
        cert = keystore.init_authority(keys_dir, convoy.name, time.time(), force=args.force)
        print(f"{cert.name}: {keys_dir}/authority.key, authority.cert (digest {cert.digest.hex()})")
    elif args.keys_command == "operator":
        cert = keystore.issue_operator(
            keys_dir, convoy.name, args.name, time.time(), force=args.force
        )
        stem = f"operator-{args.name}"
        print(f"{cert.name}: {keys_dir}/{stem}.key, {stem}.cert (digest {cert.digest.hex()})")
    else:
        if not 0 <= args.vehicle_id < convoy.n_vehicles:
            raise ConfigError(
                f"--vehicle-id {args.vehicle_id}: the convoy has vehicles 0..{convoy.n_vehicles - 1}"
            )
        n_revoked = len(keystore.load_revoked(keys_dir))
        cert = keystore.issue_vehicle(
            keys_dir, convoy.name, args.vehicle_id, time.time(), force=args.force
        )
        stem = keystore.vehicle_stem(args.vehicle_id)
        print(f"{cert.name}: {keys_dir}/{stem}.key, {stem}.cert (digest {cert.digest.hex()})")
        if len(keystore.load_revoked(keys_dir)) > n_revoked:
            print(
                f"the previous certificate of vehicle {args.vehicle_id} is revoked: copy "
                f"{keys_dir}/{keystore.REVOKED} to every vehicle"
            )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add this package's commands to ``openconvoy``'s subparsers (handlers import lazily)."""
    _add_bsm(sub)
    _add_keys(sub)
