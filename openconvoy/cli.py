"""The ``openconvoy`` command line.

Each subcommand's arguments are declared here; its work is imported lazily inside the
handler, so ``openconvoy bsm listen`` on a companion computer never imports the simulator
or the training stack. Bad arguments or configs end in one ``openconvoy: error: ...``
line and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError, OpenConvoyError


class CliError(ConfigError):
    """A user-facing error: printed as one line, exit status 2."""


Handler = Callable[[argparse.Namespace], int | None]


class _Parser(argparse.ArgumentParser):
    """Bad arguments end in one line naming the flag and what is allowed (exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"openconvoy: error: {message} (see {self.prog} --help)\n")


def _num(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         hi_open: bool = False, integer: bool = False) -> Callable[[str], Any]:
    """An argparse type: a finite number (or an integer) inside the given interval."""
    rng = Range(lo, hi, lo_open, hi_open)
    kind = "integer" if integer else "number"

    def parse(text: str) -> float | int:
        try:
            value: float | int = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an' if integer else 'a'} {kind}, got {text!r}") from None
        if not rng.contains(float(value)):
            raise argparse.ArgumentTypeError(f"{text} is out of range; allowed: {rng.describe(kind)}")
        return value

    parse.__name__ = kind
    return parse


def _int(lo: int, hi: int) -> Callable[[str], Any]:
    return _num(lo, hi, integer=True)


FRACTION = _num(0.0, 1.0)  # probabilities and packet error rates
SEED = _int(0, 2**32 - 1)
RATE_HZ = _num(0.0, 100.0, lo_open=True)  # control rates: above 100 Hz no autopilot keeps up
DURATION = _num(0.0, 7 * 86400.0, lo_open=True)  # seconds
TIMEOUT = _num(0.0, 86400.0, lo_open=True)  # seconds
SECONDS_POS = _num(0.0, 3600.0, lo_open=True)


# --- simulation (issue 2): sim, report, presets ------------------------------------------


def _run_args(p: argparse.ArgumentParser, sweep: bool) -> None:
    """Arguments shared by ``sim`` and ``experiment per-sweep`` (None = not given)."""
    p.add_argument("--scenario", default=None, metavar="SPEC",
                   help="paper (default), track, emergency-braking, track-file:PATH, or with the "
                   "traffic extra highway-cut-in, highway-merge, highway-slow-traffic, "
                   "highway-lane-drop (optionally :key=value,...)")
    p.add_argument("--loss", choices=("bernoulli", "gilbert-elliott"), default=None if sweep else "bernoulli",
                   help="loss model of every link (default bernoulli)")
    p.add_argument("--burst", type=SECONDS_POS, default=None, metavar="S",
                   help="mean loss burst of gilbert-elliott, seconds (default 1)")
    p.add_argument("--duration", type=DURATION, default=None, metavar="S", help="run length (default: the scenario's)")
    p.add_argument("--followers", type=_int(1, 1000), default=None, metavar="N", help="number of followers")
    p.add_argument("--vehicle-preset", action="append", metavar="PRESET",
                   help="vehicle preset name or .toml, repeated leader first (default: the scenario's)")
    p.add_argument("--ranging", action="store_true",
                   help="give followers a ranging sensor (used by the staleness ladder's degraded mode)")
    p.add_argument("--ranging-range", type=_num(0.0, 10_000.0, lo_open=True), default=None if sweep else 20.0, metavar="M",
                   help="that sensor's range in metres (default 20)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")


def _executor_args(p: argparse.ArgumentParser) -> None:
    """``--executor`` and ``--address`` (issue 15: sweeps, tune and train on Ray)."""
    p.add_argument("--executor", choices=("local", "ray"), default=None,
                   help="where runs execute: local processes (default) or a Ray cluster (openconvoy[cluster])")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="Ray cluster to use, HOST:PORT or auto (default: a private cluster of this machine)")


def _add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="simulate one run: log, metrics and plots",
                       description="Simulate a convoy and write DIR/log.csv, DIR/metrics.json, "
                       "DIR/run.toml and plots (trajectories, gaps, speeds).")
    p.add_argument("--policy", default="paper", metavar="SPEC",
                   help="preset (openconvoy presets; NAME+ladder), policy .toml, .zip or .npz")
    p.add_argument("--per", type=FRACTION, default=0.0, help="packet error rate 0..1 (default 0)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--out", default="runs/sim", metavar="DIR", help="output directory (default runs/sim)")
    p.add_argument("--convoy", metavar="CONVOY.toml", help="convoy file: scenario, vehicles, origin")
    p.add_argument("--latency", type=_num(0.0, 60.0), default=0.0, metavar="S", help="delivery delay, seconds")
    p.add_argument("--jitter", type=_num(0.0, 60.0), default=0.0, metavar="S", help="uniform delay jitter, seconds")
    p.add_argument("--gps-noise", type=_num(0.0, 1000.0), default=0.0, metavar="M", help="position noise std, metres")
    p.add_argument("--fault", action="append", metavar="KIND:VEHICLE@T_S",
                   help="inject a fault (repeatable): halt (brake to rest, keep broadcasting), "
                   "silent (stop broadcasting, keep driving), dead (both) or forge (a keyless "
                   "station claims to be the vehicle, 1 km ahead), e.g. dead:0@30, forge:0@10")
    p.add_argument("--auth", choices=("required", "off"), default=None,
                   help="members authenticate messages, so forgeries are rejected (default "
                   "required; a convoy file's [v2v] auth = \"off\" turns it off)")
    _run_args(p, sweep=False)

    def _sim(args: argparse.Namespace) -> int:
        from openconvoy.experiments.commands import sim

        return sim(args)

    p.set_defaults(handler=_sim)

    p = sub.add_parser("report", help="recompute metrics from a log or run directory",
                       description="Recompute the metrics from a log file or a directory of "
                       "(per-vehicle) logs, print them and write metrics.json.")
    p.add_argument("path", metavar="DIR_OR_LOG")
    p.add_argument("--convoy", metavar="CONVOY.toml",
                   help="vehicle lengths for logs without a length_m column (vehicle runs)")
    p.add_argument("--out", metavar="FILE", help="metrics file (default: metrics.json beside the log)")
    p.add_argument("--plots", action="store_true", help="also draw trajectories, gaps and speeds")

    def _report(args: argparse.Namespace) -> int:
        from openconvoy.experiments.commands import report

        return report(args)

    p.set_defaults(handler=_report)

    p = sub.add_parser("presets", help="list policy and vehicle presets")

    def _presets(args: argparse.Namespace) -> int:
        from openconvoy.experiments.commands import presets

        return presets(args)

    p.set_defaults(handler=_presets)


# --- experiments (issue 3): experiment per-sweep, compare ---------------------------------


def _add_experiments(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("experiment", help="run experiments (per-sweep)")
    esub = p.add_subparsers(dest="experiment_command", metavar="EXPERIMENT", required=True)
    p = esub.add_parser("per-sweep", help="sweep packet error rates over seeds and policies",
                        description="Run a scenario for each PER and seed (and policy), in parallel; "
                        "write summary.json, summary.csv, every run's log and the paper's figures. "
                        "--config EXPERIMENT.toml describes it all; flags given override it.")
    p.add_argument("--config", metavar="EXPERIMENT.toml", help="experiment file (a run directory's copy reruns it)")
    p.add_argument("--policy", action="append", metavar="SPEC",
                   help="policy spec; repeat to draw several (e.g. --policy paper --policy paper+ladder)")
    p.add_argument("--pers", metavar="LIST", help="comma-separated PERs (default 0,0.1,...,0.6)")
    p.add_argument("--seeds", type=_int(1, 100_000), default=None, metavar="N", help="seeds 0..N-1 per PER (default 3)")
    p.add_argument("--name", default=None, help="experiment name")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--jobs", type=_int(1, 4096), default=None, metavar="N",
                   help="runs at once (default: the cores available, or the Ray cluster's CPUs)")
    _executor_args(p)
    _run_args(p, sweep=True)

    def _per_sweep(args: argparse.Namespace) -> int:
        from openconvoy.experiments.commands import per_sweep

        return per_sweep(args)

    p.set_defaults(handler=_per_sweep)

    p = sub.add_parser("compare", help="two runs or sweeps side by side, with differences",
                       description="Metrics of two runs (log files or run directories, sim or "
                       "vehicle) or two sweeps (directories with summary.json) side by side; B - A.")
    p.add_argument("a", metavar="A")
    p.add_argument("b", metavar="B")
    p.add_argument("--convoy", metavar="CONVOY.toml", help="vehicle lengths for logs without length_m")
    p.add_argument("--out", metavar="FILE.json", help="also write the comparison as JSON")

    def _compare(args: argparse.Namespace) -> int:
        from openconvoy.experiments.commands import compare

        return compare(args)

    p.set_defaults(handler=_compare)


# --- V2V (issue 4): bsm listen / send / decode --------------------------------------------


def _add_bsm(sub: argparse._SubParsersAction) -> None:
    """``bsm listen | send | decode`` (the work is in ``openconvoy.comms.tools``)."""
    # comms.multicast.DEFAULT_GROUP / DEFAULT_PORT, spelled out to keep imports lazy
    # (tests/comms/test_cli.py checks they agree).
    DEFAULT_GROUP, DEFAULT_PORT = "ff15::4f43", 4200

    bsm = sub.add_parser(
        "bsm",
        help="J2735 BSM field tools: listen, send, decode",
        description="Field tools for the V2V layer: J2735 Basic Safety Messages (UPER "
        "MessageFrames) over IPv6 multicast, and the original implementation's JSON.",
    )
    cmds = bsm.add_subparsers(dest="bsm_command", metavar="SUBCOMMAND", required=True)

    def net_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("--iface", required=True, help="network interface, e.g. wlan0")
        p.add_argument("--group", default=DEFAULT_GROUP,
                       help=f"IPv6 multicast group (default {DEFAULT_GROUP})")
        p.add_argument("--port", type=_int(1, 65535), default=DEFAULT_PORT,
                       help=f"UDP port (default {DEFAULT_PORT})")

    p = cmds.add_parser(
        "listen",
        help="print BSMs heard on an interface, one line each",
        description="Prints every BSM heard (anyone's, not only a convoy's): temporary id, "
        "msgCnt, latitude and longitude (degrees), speed (m/s), heading (compass degrees), "
        "age (s, from secMark and this host's clock). Ctrl-C stops.",
    )
    net_args(p)
    p.add_argument("--compat", action="store_true",
                   help="also listen for the original JSON format on 224.0.0.1:5004")
    p.add_argument("--count", type=_int(1, 10**12), metavar="N", help="exit after N messages")
    p.add_argument("--timeout", type=TIMEOUT, metavar="S", help="exit after S seconds")
    p.add_argument("--convoy", metavar="CONVOY.toml",
                   help="verify signed BSMs with this convoy's certificates (its keys directory); "
                   "prints accepted/rejected per sender and a summary at exit")

    def _listen(args: argparse.Namespace) -> int:
        from openconvoy.comms import tools

        tools.listen(args.iface, group=args.group, port=args.port, compat_enabled=args.compat,
                     count=args.count, timeout_s=args.timeout, auth=_verifier(args.convoy))
        return 0

    p.set_defaults(handler=_listen)

    p = cmds.add_parser(
        "send",
        help="send test BSMs",
        description="Sends COUNT BSMs at RATE Hz from a test vehicle starting at LAT, LON "
        "and moving at SPEED along HEADING (compass degrees: 0 = north, clockwise).",
    )
    net_args(p)
    p.add_argument("--hop-limit", type=_int(1, 255), default=1, help="IPv6 hop limit (default 1)")
    p.add_argument("--count", type=_int(0, 10**12), default=10, help="messages to send (default 10)")
    p.add_argument("--rate", type=_num(0.0, 100_000.0, lo_open=True), default=10.0, metavar="HZ", help="default 10")
    p.add_argument("--lat", type=_num(-90.0, 90.0), default=28.6024, help="start latitude, degrees")
    p.add_argument("--lon", type=_num(-180.0, 180.0), default=-81.2001, help="start longitude, degrees")
    p.add_argument("--elev", type=_num(-1000.0, 10_000.0), default=0.0, help="elevation, metres (default 0)")
    p.add_argument("--speed", type=_num(0.0, 163.8), default=0.0, help="m/s (default 0)")
    p.add_argument("--heading", type=_num(0.0, 360.0, hi_open=True), default=0.0,
                   help="compass degrees, 0 = north, clockwise (default 0)")
    p.add_argument("--id", metavar="HEX", help="temporary id, 8 hex digits")
    p.add_argument("--compat-car", type=_int(0, 254), metavar="N",
                   help="also send the original JSON format as convoy position N (IPv4)")
    p.add_argument("--key", metavar="KEY",
                   help="sign as IEEE 1609.2 SPDUs with this key (its .cert beside it; a foreign "
                   "convoy's key makes a forger that has a key)")
    p.add_argument("--convoy", metavar="CONVOY.toml",
                   help="the authority for --key (default: the key's directory)")
    p.add_argument("--frame", metavar="HEX", help="replay this captured datagram COUNT times")

    def _send(args: argparse.Namespace) -> int:
        import time

        from openconvoy.comms import tools

        auth = None
        if args.key:
            from openconvoy.comms.auth import Authenticator
            from openconvoy.comms.keystore import signer_of_key

            keys = None
            if args.convoy:
                from openconvoy.convoy import load_convoy

                keys = load_convoy(args.convoy).v2v.keys
            auth = Authenticator(signer_of_key(args.key, keys, time.time()))
        n = tools.send(
            args.iface, group=args.group, port=args.port, hop_limit=args.hop_limit,
            count=args.count, rate_hz=args.rate, lat_deg=args.lat, lon_deg=args.lon,
            elev_m=args.elev, speed_mps=args.speed, heading_deg=args.heading,
            temp_id=tools.temp_id_arg(args.id) if args.id else tools.DEFAULT_SEND_ID,
            compat_car=args.compat_car, auth=auth,
            frame=tools.parse_hex(args.frame) if args.frame else None,
        )
        print(f"sent {n} BSMs on {args.iface} to [{args.group}]:{args.port}", file=sys.stderr)
        return 0

    p.set_defaults(handler=_send)

    p = cmds.add_parser(
        "decode",
        help="print one UPER MessageFrame's BSM core in physical units",
        description="Decodes a hex-encoded J2735 MessageFrame (messageId 20) and prints the "
        "core fields in physical units (latitude and longitude in degrees).",
    )
    p.add_argument("hex", nargs="+", metavar="HEX", help="the frame, hex (spaces allowed)")
    p.add_argument("--json", action="store_true", help="one JSON object instead of lines")

    def _decode(args: argparse.Namespace) -> int:
        from openconvoy.comms import tools

        data = tools.parse_hex(" ".join(args.hex))
        tools.require_codec()
        try:
            lines = tools.decode_lines(data, as_json=args.json)
        except ValueError as exc:
            raise CliError(f"not a valid J2735 BSM frame: {exc}") from None
        print("\n".join(lines))
        return 0

    p.set_defaults(handler=_decode)


def _verifier(convoy_path: str | None):
    """``bsm listen --convoy``'s verifier: the convoy authority's certificate only."""
    if not convoy_path:
        return None
    from openconvoy.comms.auth import Authenticator, Credentials
    from openconvoy.comms.keystore import load_authority
    from openconvoy.convoy import load_convoy

    v2v = load_convoy(convoy_path).v2v
    authority, _ = load_authority(v2v.keys)
    return Authenticator(Credentials(authority), window_s=v2v.replay_window_s)


# --- V2V authentication (issue 12): keys init / issue --------------------------------------


def _add_keys(sub: argparse._SubParsersAction) -> None:
    """``keys init | issue`` (the work is in ``openconvoy.comms.keystore``)."""
    keys = sub.add_parser(
        "keys", help="the convoy's signing keys: authority and vehicle certificates",
        description="IEEE 1609.2 keys for signed BSMs and aborts. The keys live in NAME.keys/ "
        "beside the convoy file (or [v2v] keys); once they exist, deploy signs and verifies "
        "every message unless the convoy says auth = \"off\".",
    )
    cmds = keys.add_subparsers(dest="keys_command", metavar="SUBCOMMAND", required=True)
    p = cmds.add_parser("init", help="make the convoy authority's key and certificate")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml")
    p.add_argument("--force", action="store_true", help="replace an existing authority")
    p.set_defaults(handler=_keys_handler)
    p = cmds.add_parser("issue", help="issue a vehicle's key and certificate")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml")
    p.add_argument("--vehicle-id", type=_int(0, 254), required=True, help="convoy index, 0 = leader")
    p.set_defaults(handler=_keys_handler)


def _keys_handler(args: argparse.Namespace) -> int:
    import time

    from openconvoy.comms import keystore
    from openconvoy.convoy import load_convoy

    convoy = load_convoy(args.convoy)
    keys_dir = convoy.v2v.keys
    if args.keys_command == "init":
        cert = keystore.init_authority(keys_dir, convoy.name, time.time(), force=args.force)
        print(f"{cert.name}: {keys_dir}/authority.key, authority.cert (digest {cert.digest.hex()})")
    else:
        if not 0 <= args.vehicle_id < convoy.n_vehicles:
            raise CliError(f"--vehicle-id {args.vehicle_id}: the convoy has vehicles 0..{convoy.n_vehicles - 1}")
        cert = keystore.issue_vehicle(keys_dir, convoy.name, args.vehicle_id, time.time())
        stem = keystore.vehicle_stem(args.vehicle_id)
        print(f"{cert.name}: {keys_dir}/{stem}.key, {stem}.cert (digest {cert.digest.hex()})")
    return 0


# --- vehicles (issue 5): deploy, abort, vehicle --sim, fit-plant, demo --------------------


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
    p.add_argument("--preset", default=None,
                   help="move like this vehicle preset (name or .toml) instead of the recorded "
                   "firmware's loops and vehicle model (the default)")
    p.add_argument("--timing", choices=("short", "firmware"), default="short",
                   help="boot/arming timeline: short (armable after --ready-after) or the "
                   "recorded firmware's (ArduPilot GUIDED ~42 s, PX4 ~3.7 s)")
    p.add_argument("--no-rc-switch", action="store_true",
                   help="ArduPilot: no RC mode switch reading (MANUAL) 0.42 s after boot")
    p.add_argument("--speedup", type=_num(0.0, 1000.0, lo_open=True), default=1.0, metavar="X",
                   help="run the vehicle's clock X times faster than real time (default 1)")
    p.add_argument("--boot-on-connect", action="store_true",
                   help="boot when the first MAVLink message arrives (as SITL waiting for serial0)")
    p.add_argument("--home", default="52.0,4.37,0", metavar="LAT,LON,ALT")
    p.add_argument("--start", default="0,0,0", metavar="X,Y,HEADING_DEG",
                   help="ENU metres around home; heading degrees, 0 = east, counter-clockwise")
    p.add_argument("--ready-after", type=_num(0.0, 3600.0), default=5.0, metavar="S",
                   help="seconds until arming is possible (default 5)")
    p.add_argument("--setpoint-timeout", type=_num(0.0, 600.0, lo_open=True), default=3.0, metavar="S",
                   help="ArduPilot GUIDED stops after this long without setpoints (default 3)")
    p.add_argument("--max-rate", type=_num(0.0, 1000.0, lo_open=True), default=None, metavar="HZ",
                   help="refuse telemetry rates above HZ (default: the firmware's rule, "
                   "ArduPilot < 50 Hz)")
    p.add_argument("--gps-noise", type=_num(0.0, 1000.0), default=0.0, metavar="M", help="position noise std")
    p.add_argument("--seed", type=SEED, default=0)

    def _vehicle(args: argparse.Namespace) -> int:
        from openconvoy.bridge.simvehicle import run_vehicle_cli

        return run_vehicle_cli(args)

    p.set_defaults(handler=_vehicle)

    p = sub.add_parser(
        "fit-plant",
        help="fit a vehicle preset (lag, accel limits, turn rate, delay) from a vehicle run's logs",
        description="Replays the logged commands through the simulator's plant model and fits "
        "speed lag, acceleration/deceleration limits, turn-rate limit, heading lag and "
        "actuation delay; writes a preset TOML that sim and experiment accept.",
    )
    p.add_argument("log", metavar="LOG_DIR", nargs="+",
                   help="a run directory of per-vehicle logs, or one log; with --model pi also "
                   "MAVLink recordings (.jsonl.gz, as in shared/sitl), several allowed")
    p.add_argument("--model", choices=("lag", "pi"), default="lag",
                   help="lag: first-order speed lag (default); pi: the autopilot's PI speed loop "
                   "with its delay, accel ramp and static friction, and its heading loop")
    p.add_argument("--source", choices=("telemetry", "truth"), default="telemetry",
                   help="recordings: fit GLOBAL_POSITION_INT/ATTITUDE (default) or PX4 SIH's "
                   "true state (HIL_STATE_QUATERNION)")
    p.add_argument("--out", metavar="PRESET.toml", help="output file (default NAME.toml)")
    p.add_argument("--name", default="fitted", help="preset name (default fitted)")
    p.add_argument("--base", default="1/10",
                   help="preset giving what logs cannot show: size, steering, speed cap (default 1/10)")
    p.add_argument("--vehicle-id", type=_int(0, 254), help="which vehicle, when the logs hold several")
    p.add_argument("--cmd-timing", choices=("after-state", "before-state"), default="after-state",
                   help="a row's command was computed from its state (OpenConvoy's sim and "
                   "vehicle logs) or led to it (some other tools' logs)")

    def _fit_plant(args: argparse.Namespace) -> int:
        from openconvoy.bridge.fitplant import run_fit_plant_cli

        return run_fit_plant_cli(args)

    p.set_defaults(handler=_fit_plant)
    _add_deploy_commands(sub)


def _add_deploy_commands(sub: argparse._SubParsersAction) -> None:
    """``deploy``, ``abort``, ``demo`` (bridge.deploy, bridge.demo)."""
    p = sub.add_parser(
        "deploy",
        help="drive a vehicle with a policy over MAVLink, talking V2V over IPv6 multicast",
        description="The real-time loop on a vehicle: telemetry -> convoy member -> policy -> "
        "setpoints, with BSMs over IPv6 multicast, failsafes and a safety envelope. "
        "SIGINT/SIGTERM: stop, HOLD, save the log, exit 0.",
    )
    p.add_argument("--policy", required=True, help="preset name, policy .toml, .zip or .npz")
    p.add_argument("--vehicle-id", type=_int(0, 254), required=True, help="convoy index, 0 = leader")
    p.add_argument("--convoy", required=True, metavar="CONVOY.toml", help="the convoy config")
    p.add_argument("--mavlink", required=True, metavar="URL",
                   help="autopilot link: /dev/ttyX (with --baud), udp:, udpin:, udpout:, tcp:")
    p.add_argument("--iface", required=True, help="network interface for V2V multicast")
    p.add_argument("--per", type=FRACTION, default=0.0, help="emulated packet error rate 0..1")
    p.add_argument("--drop-at", choices=("receiver", "sender"), default="receiver",
                   help="where the emulated loss drops messages (default receiver)")
    p.add_argument("--log", metavar="DIR", help="write DIR/vehicle_N.csv and DIR/vehicle_N.json")
    p.add_argument("--rate", type=RATE_HZ, metavar="HZ", help="control rate (default: the policy's)")
    p.add_argument("--dry-run", action="store_true", help="everything but arming and setpoints")
    p.add_argument("--passive", action="store_true",
                   help="leader driven by a person: broadcast and log only")
    p.add_argument("--track", metavar="FILE", help="leader follows this OpenConvoy JSON track")
    p.add_argument("--duration", type=DURATION, metavar="S",
                   help="end after S seconds of driving (default: the leader's scenario)")
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
    p.add_argument("--repeat", type=_int(1, 1000), default=3, help="send this many times (default 3)")
    p.add_argument("--key", metavar="KEY",
                   help="sign the abort with this private key (its .cert beside it), e.g. "
                   "NAME.keys/authority.key; required when the convoy has keys")

    def _abort(args: argparse.Namespace) -> int:
        from openconvoy.bridge.deploy import abort_from_namespace

        return abort_from_namespace(args)

    p.set_defaults(handler=_abort)

    p = sub.add_parser(
        "demo",
        help="three simulated vehicles driven by three deploy processes over MAVLink + multicast",
        description="Runs the paper scenario with three simulated MAVLink vehicles and three "
        "`openconvoy deploy` processes inside a private network namespace (BSMs over real IPv6 "
        "multicast that never leaves the machine), then compares with the pure simulation.",
    )
    p.add_argument("--policy", default="paper", help="policy spec (default paper)")
    p.add_argument("--per", type=FRACTION, default=0.0, help="emulated packet error rate")
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot")
    p.add_argument("--duration", type=DURATION, metavar="S",
                   help="shorten the scenario to S seconds (default: all 60 s)")
    p.add_argument("--out", metavar="DIR", help="keep the run here (default a temporary dir)")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON at the end")

    def _demo(args: argparse.Namespace) -> int:
        from openconvoy.bridge.demo import demo_from_namespace

        return demo_from_namespace(args)

    p.set_defaults(handler=_demo)


# --- learning (issue 6): train, tune, export ----------------------------------------------


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a follower policy (PPO/SAC, shared by all followers)",
                       description="Train one policy for every follower with stable-baselines3 under "
                       "domain randomization; write RUN_DIR/policy.zip (with its layout, member config "
                       "and control rate), config.toml, checkpoints/ and TensorBoard logs (tb/). "
                       "--config TRAIN.toml (a run's config.toml) describes it all; flags override it.")
    p.add_argument("--config", metavar="TRAIN.toml", action="append",
                   help="training config file; repeat for one run per config (OUT/<stem>)")
    p.add_argument("--algo", choices=("ppo", "sac"), help="algorithm (default ppo)")
    p.add_argument("--steps", type=_int(1, 10**12), metavar="N", help="agent steps (default 600000)")
    p.add_argument("--out", default="runs/train", metavar="RUN_DIR", help="run directory (default runs/train)")
    p.add_argument("--seed", type=SEED, help="seed (default 0)")
    p.add_argument("--seeds", type=SEED, nargs="+", metavar="S",
                   help="one run per seed (OUT/seed_S), run as tasks of --executor")
    p.add_argument("--jobs", type=_int(1, 4096), metavar="N",
                   help="training runs at once (default: the cores available, or the cluster's CPUs)")
    _executor_args(p)
    p.add_argument("--envs", type=_int(1, 1024), metavar="N", help="environments stepped together (default 4)")
    p.add_argument("--followers", type=_int(1, 1000), metavar="N", help="followers per environment (default 2)")
    p.add_argument("--base", metavar="SPEC", help="classical policy the network corrects (residual; "
                   "default paper), or 'none' for absolute actions")
    p.add_argument("--M", type=_int(1, 1000), help="observation: predecessors per observation (default: the base's)")
    p.add_argument("--k", type=_int(1, 1000), help="observation: states per vehicle (default: the base's)")
    p.add_argument("--rate", type=RATE_HZ, metavar="HZ", help="control rate (default: the base's, 20)")
    p.add_argument("--per-range", type=FRACTION, nargs=2, metavar=("A", "B"), help="PER drawn in [A, B] (default 0 0.6)")
    p.add_argument("--burst-prob", type=FRACTION, metavar="P", help="chance of Gilbert-Elliott bursts per episode (default 0.3)")
    p.add_argument("--latency-range", type=_num(0.0, 60.0), nargs=2, metavar=("A", "B"), help="latency, seconds (default 0 0.05)")
    p.add_argument("--gps-noise-range", type=_num(0.0, 1000.0), nargs=2, metavar=("A", "B"), help="GPS noise std, metres (default 0 0.05)")
    p.add_argument("--scenarios", nargs="+", metavar="SPEC", help="scenarios drawn per episode (default paper)")
    p.add_argument("--vehicles", nargs="+", metavar="PRESET", help="vehicle presets or fitted preset .toml files drawn per vehicle (default 1/10 1/6)")
    p.add_argument("--threads", type=_int(1, 1024), metavar="N", help="torch CPU threads (default 1)")
    p.add_argument("--overwrite", action="store_true", help="replace a policy already in RUN_DIR")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def _train(args: argparse.Namespace) -> int:
        from openconvoy.train.cli import train_command

        return train_command(args)

    p.set_defaults(handler=_train)

    p = sub.add_parser("tune", help="tune a classical policy's parameters with Optuna",
                       description="Search a classical policy's PD/PID gains, steering gain and spacing "
                       "shape against the metrics over PERs and seeds; write the best as a policy "
                       "TOML file (--policy accepts it) and OUT.json with the study's numbers.")
    p.add_argument("--policy", default="paper", metavar="BASE", help="preset or policy .toml to start from")
    p.add_argument("--trials", type=_int(1, 10**7), default=30, metavar="N")
    p.add_argument("--out", default="tuned.toml", metavar="FILE.toml")
    p.add_argument("--per", type=FRACTION, nargs="+", default=[0.0, 0.3, 0.6], metavar="PER", help="PERs (default 0 0.3 0.6)")
    p.add_argument("--seeds", type=SEED, nargs="+", default=[1000, 1001], metavar="S",
                   help="seeds (default 1000 1001, apart from the 0.. of reports)")
    p.add_argument("--scenario", default="paper", metavar="SPEC")
    p.add_argument("--duration", type=DURATION, metavar="S", help="run length (default: the scenario's)")
    p.add_argument("--params", nargs="+", metavar="PATH", help="parameters (default: those the policy uses)")
    p.add_argument("--seed", type=SEED, default=0, help="sampler seed")
    p.add_argument("--storage", metavar="URL_OR_FILE",
                   help="keep the study: an Optuna RDB URL (sqlite:///study.db, postgresql://...) "
                   "or a journal file path; rerunning with it resumes the study")
    p.add_argument("--study-name", metavar="NAME", help="the study in --storage (default: OUT's stem)")
    p.add_argument("--jobs", type=_int(1, 4096), metavar="N",
                   help="trials at once (default 1 locally, the cluster's CPUs on Ray)")
    _executor_args(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def _tune(args: argparse.Namespace) -> int:
        from openconvoy.train.cli import tune_command

        return tune_command(args)

    p.set_defaults(handler=_tune)

    p = sub.add_parser("export", help="export a trained policy to a numpy-only .npz",
                       description="Turn RUN_DIR/policy.zip (or a .zip) into a .npz that runs without "
                       "torch (weights, observation normalization, action scaling, layout, member "
                       "config, control rate), and check its actions against SB3's predict.")
    p.add_argument("run", metavar="RUN_DIR", help="run directory or SB3 .zip")
    p.add_argument("--out", required=True, metavar="FILE.npz")

    def _export(args: argparse.Namespace) -> int:
        from openconvoy.train.cli import export_command

        return export_command(args)

    p.set_defaults(handler=_export)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="openconvoy",
        description="Cooperative driving in simulation and on PX4/ArduPilot vehicles.",
    )
    from openconvoy import __version__

    parser.add_argument("--version", action="version", version=f"openconvoy {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_sim, _add_experiments, _add_bsm, _add_keys, _add_bridge, _add_train):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``openconvoy`` console script."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad argument (one line printed)
        return exc.code if isinstance(exc.code, int) else 2
    if args.command is None:
        parser.print_help()
        return 2
    import logging

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    handler: Handler = args.handler
    try:
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except OpenConvoyError as exc:  # what a user can get wrong; anything else is a bug
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:
            raise
        # The file system said no (permissions, a directory where a file should be, a full
        # disk): the file and the reason, not a traceback.
        print(f"openconvoy: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
