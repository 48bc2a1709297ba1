"""Convoy keys made once per test session (a convoy "lab" of three, and a foreign one)."""

from __future__ import annotations

import functools
import tempfile
import time
from pathlib import Path

from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.auth import Credentials

#: Certificates start an hour before this and last a year: any test clock near it works.
T0 = time.time()


@functools.cache
def keys_dir(convoy: str, n: int = 3) -> Path:
    d = Path(tempfile.mkdtemp(prefix=f"oc-keys-{convoy}-")) / f"{convoy}.keys"
    ks.init_authority(d, convoy, T0)
    for i in range(n):
        ks.issue_vehicle(d, convoy, i, T0)
    return d


def creds(i: int, convoy: str = "lab") -> Credentials:
    return ks.load_vehicle(keys_dir(convoy), i, T0)
