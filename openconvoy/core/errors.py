"""OpenConvoy's error types: what a user can get wrong, as opposed to a bug.

Every error a person can cause with a flag, a config file, an input file, a missing
package or an unreachable vehicle is an ``OpenConvoyError``: the CLI prints its message
as one line (``openconvoy: error: ...``) and exits with status 2. Anything else reaching
the CLI is a bug and shows its traceback. Messages name what is wrong and what is allowed:
the flag, the file and key, or the file and line. It sits in ``core`` so that every
layer may raise them (DESIGN.md's import rule).

The config and input-file errors are also ``ValueError`` s (and the missing-file error a
``FileNotFoundError``, the dependency error a ``ModuleNotFoundError``), so library code
that catches those keeps working. This module imports nothing.
"""

from __future__ import annotations


class OpenConvoyError(Exception):
    """Base of every error a user can cause; its message is one line."""


class ConfigError(OpenConvoyError, ValueError):
    """A bad value in a config file (``file: key: ...``) or on the command line
    (``--flag: ...``): wrong type, out of range, unknown key."""


class InputFileError(OpenConvoyError, ValueError):
    """An input file that cannot be read or is not what it should be (a log, a track, a
    policy archive): the message names the file and, where one applies, the line."""


class MissingFileError(InputFileError, FileNotFoundError):
    """An input file that does not exist."""


class OutputPathError(OpenConvoyError, ValueError):
    """An output path that cannot be written (an existing file where a directory is
    wanted, a directory without write permission)."""


class DependencyMissing(OpenConvoyError, ModuleNotFoundError):
    """An optional package a command needs is not installed; the message names the extra
    (``pip install 'openconvoy[vehicle]'``)."""


class LinkError(OpenConvoyError):
    """A vehicle or network link that cannot be used: no answer, refused command, lost
    connection, unknown interface."""


__all__ = [
    "ConfigError",
    "DependencyMissing",
    "InputFileError",
    "LinkError",
    "MissingFileError",
    "OpenConvoyError",
    "OutputPathError",
]
