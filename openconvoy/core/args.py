"""argparse value types: finite numbers inside declared ranges (``core.config.Range``).

Shared by every subpackage's ``cli`` module, so that a bad number is one line naming the
flag and the interval allowed, the same everywhere. Units are the flags' own (seconds, Hz).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from openconvoy.core.config import Range


def number(
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    integer: bool = False,
) -> Callable[[str], Any]:
    """An argparse type: a finite number (or an integer) inside the given interval."""
    rng = Range(lo, hi, lo_open, hi_open)
    kind = "integer" if integer else "number"

    def parse(text: str) -> float | int:
        try:
            value: float | int = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an' if integer else 'a'} {kind}, got {text!r}"
            ) from None
        if not rng.contains(float(value)):
            raise argparse.ArgumentTypeError(
                f"{text} is out of range; allowed: {rng.describe(kind)}"
            )
        return value

    parse.__name__ = kind
    return parse


def integer(lo: int, hi: int) -> Callable[[str], Any]:
    return number(lo, hi, integer=True)


FRACTION = number(0.0, 1.0)  # probabilities and packet error rates
SEED = integer(0, 2**32 - 1)
RATE_HZ = number(0.0, 100.0, lo_open=True)  # control rates: above 100 Hz no autopilot keeps up
DURATION = number(0.05, 7 * 86400.0)  # seconds: at least one control period at 20 Hz
TIMEOUT = number(0.0, 86400.0, lo_open=True)  # seconds
SECONDS_POS = number(0.0, 3600.0, lo_open=True)


Flags = tuple[tuple[str, dict[str, Any]], ...]
"""A command's flags as data: (name, ``add_argument`` keywords) pairs, in help order."""


def add_flags(parser: argparse.ArgumentParser, flags: Flags) -> None:
    """Add every flag of ``flags`` to ``parser``, in order."""
    for name, kwargs in flags:
        parser.add_argument(name, **kwargs)


def lazy_handler(module: str, name: str) -> Callable[[argparse.Namespace], int]:
    """A command handler that imports ``module`` only when the command runs (so that
    ``openconvoy --help`` loads no heavy dependency) and returns ``module.name(args)``."""

    def handler(args: argparse.Namespace) -> int:
        import importlib

        result: int = getattr(importlib.import_module(module), name)(args)
        return result

    handler.__name__ = name
    return handler


def add_command(
    sub: argparse._SubParsersAction,
    name: str,
    flags: Flags,
    handler: Callable[[argparse.Namespace], int],
    **parser_kwargs: Any,
) -> argparse.ArgumentParser:
    """A subcommand ``name`` (``help``, ``description``, ... in ``parser_kwargs``) with its
    ``flags``, run by ``handler``; returns its parser."""
    parser = sub.add_parser(name, **parser_kwargs)
    add_flags(parser, flags)
    parser.set_defaults(handler=handler)
    return parser


POLICY_ARG_HELP = (
    "keyword argument of a Python plug-in policy (module:Name, file.py:Name), repeatable; "
    "values as TOML scalars (0.5, 3, true, text)"
)


def add_policy_arg(parser: argparse.ArgumentParser) -> None:
    """``--policy-arg KEY=VALUE`` (repeatable): folded into ``--policy`` by ``cli.main``
    (``policies.spec.with_policy_args``)."""
    parser.add_argument(
        "--policy-arg", action="append", metavar="KEY=VALUE", default=None, help=POLICY_ARG_HELP
    )
