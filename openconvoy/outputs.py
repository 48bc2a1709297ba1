"""Output paths checked before any work starts (before a vehicle is armed, before a long
simulation runs), so that a bad ``--log`` or ``--out`` ends in one line naming it, never in
a traceback after the work is done or the vehicle moved."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from openconvoy.core.errors import OutputPathError


def check_output_dir(path: str | Path, what: str, create: bool = True) -> Path:
    """Make sure directory ``path`` exists (created if need be) and is writable; ``what``
    names the flag in the error (``OutputPathError``). With ``create`` False nothing is
    created: the nearest existing ancestor must be a directory we may write in."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputPathError(f"{what} {p}: exists and is not a directory")
    if not create and not p.exists():
        ancestor = p.absolute().parent
        while not ancestor.exists():
            ancestor = ancestor.parent
        if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
            raise OutputPathError(
                f"{what} {p}: cannot create it ({ancestor} is not a writable directory)"
            )
        return p
    try:
        p.mkdir(parents=True, exist_ok=True)
        # Creating a file is the only reliable test (os.access ignores read-only mounts).
        with tempfile.NamedTemporaryFile(dir=p, prefix=".openconvoy-write-test-"):
            pass
    except OSError as exc:
        raise OutputPathError(f"{what} {p}: cannot write there ({exc.strerror or exc})") from None
    return p


def check_output_file(path: str | Path, what: str) -> Path:
    """Make sure file ``path`` can be written (its directory created if need be; an
    existing file is replaced later, a directory is refused)."""
    p = Path(path)
    if p.is_dir():
        raise OutputPathError(f"{what} {p}: is a directory; give a file name")
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputPathError(f"{what} {p}: the file exists and is not writable")
    check_output_dir(p.parent if str(p.parent) else Path("."), f"{what} directory")
    return p
