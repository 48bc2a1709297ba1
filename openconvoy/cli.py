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


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


Handler = Callable[[argparse.Namespace], int | None]


# --- simulation (issue 2): sim, report, presets ------------------------------------------


def _add_sim(sub: argparse._SubParsersAction) -> None:
    pass  # filled by the simulation work


# --- experiments (issue 3): experiment per-sweep, compare ---------------------------------


def _add_experiments(sub: argparse._SubParsersAction) -> None:
    pass  # filled by the experiments work


# --- V2V (issue 4): bsm listen / send / decode --------------------------------------------


def _add_bsm(sub: argparse._SubParsersAction) -> None:
    pass  # filled by the comms work


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
    p.add_argument("--id", type=int, required=True, help="MAVLink system id (1..254)")
    p.add_argument("--mavlink", required=True, metavar="URL", help="e.g. udpin:127.0.0.1:14551")
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot")
    p.add_argument("--preset", default="1/10", help="vehicle preset name or .toml (default 1/10)")
    p.add_argument("--home", default="52.0,4.37,0", metavar="LAT,LON,ALT")
    p.add_argument("--start", default="0,0,0", metavar="X,Y,HEADING_DEG",
                   help="ENU metres around home; heading degrees, 0 = east, counter-clockwise")
    p.add_argument("--ready-after", type=float, default=5.0, metavar="S",
                   help="seconds until arming is possible (default 5)")
    p.add_argument("--setpoint-timeout", type=float, default=3.0, metavar="S",
                   help="ArduPilot GUIDED stops after this long without setpoints (default 3)")
    p.add_argument("--max-rate", type=float, default=40.0, metavar="HZ",
                   help="fastest telemetry rate accepted (default 40)")
    p.add_argument("--gps-noise", type=float, default=0.0, metavar="M", help="position noise std")
    p.add_argument("--seed", type=int, default=0)

    def _vehicle(args: argparse.Namespace) -> int:
        from openconvoy.bridge.simvehicle import run_vehicle_cli

        return run_vehicle_cli(args)

    p.set_defaults(handler=_vehicle)


# --- learning (issue 6): train, tune, export ----------------------------------------------


def _add_train(sub: argparse._SubParsersAction) -> None:
    pass  # filled by the training work


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="openconvoy",
        description="Cooperative driving in simulation and on PX4/ArduPilot vehicles.",
    )
    from openconvoy import __version__

    parser.add_argument("--version", action="version", version=f"openconvoy {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_sim, _add_experiments, _add_bsm, _add_bridge, _add_train):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``openconvoy`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
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
    except (CliError, ValueError, FileNotFoundError, KeyError) as exc:
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"openconvoy: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
