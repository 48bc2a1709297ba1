"""The ``openconvoy`` command line.

Each subpackage declares its own subcommands (``experiments.cli``, ``comms.cli``,
``bridge.cli``, ``train.cli``: a ``register(subparsers)`` each; ``demo``, which composes them
all, is declared here). Those modules import only argparse and ``core``; a command's work is
imported lazily inside its handler, so ``openconvoy bsm listen`` on a companion computer
never imports the simulator or the training stack. Bad arguments or configs end in one ``openconvoy: error: ...``
line and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from openconvoy.core.args import DURATION, FRACTION, add_policy_arg, lazy_handler
from openconvoy.core.errors import ConfigError, OpenConvoyError


class CliError(ConfigError):
    """A user-facing error: printed as one line, exit status 2."""


EXTRAS: dict[str, str] = {
    "matplotlib": "plots",
    "asn1tools": "vehicle",
    "cryptography": "vehicle",
    "pymavlink": "vehicle",
    "serial": "vehicle",
    "torch": "train",
    "stable_baselines3": "train",
    "supersuit": "train",
    "optuna": "train",
    "tensorboard": "train",
    "highway_env": "traffic",
    "numba": "batched",
    "ray": "cluster",
    "cyclonedds": "px4dds",
}
"""The optional packages, by import name, and the extra (pyproject.toml) that brings each."""


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """One line naming the extra to install when ``exc`` is an optional package missing
    (None when it is anything else: a bug, shown with its traceback)."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRAS.get(top)
    if extra is None:
        return None
    return (
        f"this command needs the '{extra}' extra ({top} is not installed): "
        f"pip install 'openconvoy[{extra}]' (from a clone: pip install -e '.[{extra}]')"
    )


Handler = Callable[[argparse.Namespace], int | None]


class _Parser(argparse.ArgumentParser):
    """Bad arguments end in one line naming the flag and what is allowed (exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"openconvoy: error: {message} (see {self.prog} --help)\n")


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """``demo``: composes vehicles, deploys and the simulator (``openconvoy.demo``)."""
    p = sub.add_parser(
        "demo",
        help="three simulated vehicles driven by three deploy processes over MAVLink + multicast",
        description="Runs the paper scenario with three simulated MAVLink vehicles and three "
        "`openconvoy deploy` processes inside a private network namespace (BSMs over real IPv6 "
        "multicast that never leaves the machine), then compares with the pure simulation.",
    )
    p.add_argument("--policy", default="paper", help="policy spec (default paper)")
    add_policy_arg(p)
    p.add_argument("--per", type=FRACTION, default=0.0, help="emulated packet error rate")
    p.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot")
    p.add_argument(
        "--duration",
        type=DURATION,
        metavar="S",
        help="shorten the scenario to S seconds (default: all 60 s)",
    )
    p.add_argument("--out", metavar="DIR", help="keep the run here (default a temporary dir)")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON at the end")
    p.add_argument(
        "--link",
        default="mavlink",
        metavar="LINK[,LINK,LINK]",
        help="how the deploys reach the vehicles: MAVLink (default), MAVROS stand-ins on a "
        "private roscore or ROS 2 (mavros, with --ros; or mavros-ros1, mavros-ros2), PX4 DDS "
        "stand-ins (px4-dds, needs --autopilot px4), or ArduPilot AP_DDS stand-ins on ROS 2 "
        "(ap-dds); one for all, or one per vehicle, leader first (e.g. mavlink,mavros-ros2,"
        "ap-dds: written as the convoy file's [[vehicle]] tables; docs/ros.md)",
    )
    p.add_argument(
        "--ros",
        type=int,
        choices=(1, 2),
        default=1,
        help="ROS version of --link mavros: 1 (a private roscore) or 2 (rclpy, make ros2)",
    )
    p.add_argument("--bag", action="store_true", help="the deploys also record ROS 2 bags")
    p.add_argument(
        "--v2v",
        choices=("multicast", "ros2"),
        default="multicast",
        help="what carries V2V: IPv6 multicast (default) or a ROS 2 topic over DDS (docs/ros.md)",
    )

    p.set_defaults(handler=lazy_handler("openconvoy.demo", "demo_from_namespace"))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="openconvoy",
        description="Cooperative driving in simulation and on PX4/ArduPilot vehicles.",
    )
    from openconvoy import __version__

    parser.add_argument("--version", action="version", version=f"openconvoy {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # Each subpackage declares its own commands; its ``cli`` module is light (argparse and
    # ``core`` only) and the work behind a command is imported when it runs.
    from openconvoy.bridge import cli as bridge_cli
    from openconvoy.comms import cli as comms_cli
    from openconvoy.experiments import cli as experiments_cli
    from openconvoy.train import cli as train_cli

    experiments_cli.register(sub)
    comms_cli.register(sub)
    bridge_cli.register(sub)
    _add_demo(sub)
    train_cli.register(sub)
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
        _fold_policy_args(args)
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader left (`openconvoy presets | head`): stop quietly, as `cat` does. Python's
        # documented recipe: point stdout at devnull so the exit-time flush does not raise.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a command killed by the pipe
    except OpenConvoyError as exc:  # what a user can get wrong; anything else is a bug
        print(f"openconvoy: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:  # an optional package of an extra not installed
        line = missing_extra(exc)
        if line is None:
            raise
        print(f"openconvoy {args.command}: error: {line}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:
            raise
        # The file system said no (permissions, a directory where a file should be, a full
        # disk): the file and the reason, not a traceback.
        print(f"openconvoy: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return 2


def _fold_policy_args(args: argparse.Namespace) -> None:
    """``--policy-arg KEY=VALUE`` folded into ``--policy`` (every spec given) as
    ``?KEY=VALUE``, so the arguments travel with the spec to every run and process."""
    extra = getattr(args, "policy_arg", None)
    if not extra:
        return
    from openconvoy.policies.spec import with_policy_args

    for attr in ("policy", "base"):
        value = getattr(args, attr, None)
        if isinstance(value, str):
            setattr(args, attr, with_policy_args(value, extra))
            return
        if isinstance(value, list):
            setattr(args, attr, [with_policy_args(v, extra) for v in value])
            return
    raise CliError("--policy-arg: give --policy (or train's --base), a Python plug-in policy, too")


if __name__ == "__main__":
    sys.exit(main())
