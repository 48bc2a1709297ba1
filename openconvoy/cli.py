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
    pass  # filled by the bridge work


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
