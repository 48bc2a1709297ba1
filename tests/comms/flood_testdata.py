"""Wrongly signed BSM floods as D52's attacker makes them: a captured SPDU of the leader (signed
by its certificate digest), with a fresh generation time and a random ``s`` each."""

from __future__ import annotations

import random

from openconvoy.comms.security import certs as c
from openconvoy.comms.security import spdu as sp


class Forger:
    """Copies of one captured digest-signed SPDU, re-stamped; none verifies."""

    def __init__(self, captured: bytes, seed: int = 0) -> None:
        spdu = sp.decode_signed(captured)
        assert spdu.certificate is None, "capture a digest-signed SPDU"
        stamp = spdu.generation_time.to_bytes(8, "big")
        self._at = captured.index(stamp)
        self._frame = bytearray(captured)
        self._rng = random.Random(seed)

    def frame(self, t_unix: float) -> bytes:
        """A copy generated at ``t_unix`` (s) with a random signature ``s``."""
        f = self._frame
        f[self._at : self._at + 8] = c.time64(t_unix).to_bytes(8, "big")
        f[-32:] = self._rng.randbytes(32)
        return bytes(f)
