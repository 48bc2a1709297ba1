"""Signed-BSM speed: sign + verify pairs per second and the verifying receiver's messages
per second, on one core, printed as one JSON line.

Cases (ECDSA NIST P-256 through ``cryptography``/OpenSSL; SPDUs through asn1tools OER):

- ``sign_verify_pairs``: ``Authenticator.sign`` of a BSM frame (a digest signer), then
  ``decode_signed`` and one ECDSA verification, what a sender and a receiver each pay;
- ``sign``, ``verify``: each half alone (``verify`` = parse + check of a known signer);
- ``receiver_verified_msgs``: ``Receiver.handle`` on signed BSMs from 10 members (each
  certificate learned once, then digests), all checks on: signature, freshness, duplicate
  and order, the member binding, then the BSM decode and mapping. The issue's aim is
  >= 5,000/s (100 vehicles at 10 Hz with 5x headroom);
- ``receiver_unsigned_msgs``: the same receiver path without authentication.

``*_per_s`` are per CPU second of this process (best of ``--repeat``).

    python benchmarks/bench_auth.py [--messages 6000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from importlib.metadata import version

from openconvoy.comms import bsm as j
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.security.certs import PSID_BSM
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import Receiver, Sender
from openconvoy.core.state import VehicleState

N_SENDERS = 10


def _best(fn, n: int, repeat: int) -> float:
    best = 0.0
    for _ in range(repeat):
        t0 = time.process_time()
        fn(n)
        best = max(best, n / (time.process_time() - t0))
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=6000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()

    now = time.time()
    keys = os.path.join(tempfile.mkdtemp(prefix="bench-auth-"), "bench.keys")
    ks.init_authority(keys, "bench", now)
    for i in range(N_SENDERS + 1):
        ks.issue_vehicle(keys, "bench", i, now)
    origin = Origin(28.6024, -81.2001, 20.0)
    ids = TempIds("bench", N_SENDERS + 1)
    creds = [ks.load_vehicle(keys, i, now) for i in range(N_SENDERS + 1)]
    senders = [
        Sender(ids, origin, i, auth=Authenticator(creds[i])) for i in range(1, N_SENDERS + 1)
    ]
    plain = [Sender(ids, origin, i) for i in range(1, N_SENDERS + 1)]

    def frames(pool: list[Sender], n: int, t0: float) -> list[tuple[bytes, float]]:
        # 10 Hz per sender; receive times 20 ms after generation (the clock is injected)
        out = []
        for k in range(n):
            s = pool[k % len(pool)]
            t = t0 + 0.1 * (k // len(pool))
            st = VehicleState(s.vehicle_index, t, 30.0 - 15.0 * s.vehicle_index, 0.0, 1.5, 0.0)
            out.append((s.datagrams(st, t)[0], t + 0.02))
        return out

    n = a.messages
    signed = frames(senders, n, now)
    unsigned = frames(plain, n, now)
    core = j.decode_frame(sp.decode_signed(signed[0][0]).payload).core
    payload = j.encode_frame(core)
    signer = Authenticator(creds[1])
    signer.sign(payload, PSID_BSM, now)  # the certificate goes out first; digests after
    one = signer.sign(payload, PSID_BSM, now + 0.1)
    cert = creds[1].certificate

    def sign(m: int) -> None:
        for k in range(m):
            signer.sign(payload, PSID_BSM, now + 0.2 + k * 1e-3)

    def verify(m: int) -> None:
        from openconvoy.comms.security.certs import verify as ecdsa_verify

        for _ in range(m):
            x = sp.decode_signed(one)
            ecdsa_verify(cert.public_key, x.r, x.s, x.tbs, cert.coer)

    def pairs(m: int) -> None:
        from openconvoy.comms.security.certs import verify as ecdsa_verify

        for k in range(m):
            x = sp.decode_signed(signer.sign(payload, PSID_BSM, now + 0.2 + k * 1e-3))
            ecdsa_verify(cert.public_key, x.r, x.s, x.tbs, cert.coer)

    def receive(pool: list[tuple[bytes, float]], auth: bool) -> tuple[float, int]:
        best, delivered = 0.0, 0
        for _ in range(a.repeat):  # a fresh receiver each time (the replay checks remember)
            rx = Receiver(ids, origin, 0, auth=Authenticator(creds[0]) if auth else None)
            t0 = time.process_time()
            got = sum(rx.handle(data, t_rx) is not None for data, t_rx in pool)
            best = max(best, len(pool) / (time.process_time() - t0))
            delivered = got
        return best, delivered

    r = a.repeat
    warm = max(200, n // 20)
    pairs(warm)
    result: dict[str, object] = {"benchmark": "auth"}
    result["sign_verify_pairs_per_s"] = round(_best(pairs, max(1000, n // 3), r))
    result["sign_per_s"] = round(_best(sign, max(1000, n // 3), r))
    result["verify_per_s"] = round(_best(verify, max(1000, n // 3), r))
    rate, got = receive(signed, True)
    result["receiver_verified_msgs_per_s"] = round(rate)
    result["receiver_verified_delivered"] = f"{got}/{n}"
    rate, got = receive(unsigned, False)
    result["receiver_unsigned_msgs_per_s"] = round(rate)
    result.update(
        {
            "target_verified_msgs_per_s": 5000,
            "signed_bsm_bytes": len(one),
            "signed_bsm_with_certificate_bytes": len(signed[0][0]),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "cryptography": version("cryptography"),
            "asn1tools": version("asn1tools"),
            "python": platform.python_version(),
            "machine": platform.machine(),
        }
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
