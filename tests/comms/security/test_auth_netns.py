"""``bsm listen --convoy`` verifying what ``bsm send`` puts on a private namespace's link:
a member's signed BSMs, an unsigned forger, a forger with another convoy's key, a replay."""

from __future__ import annotations

import sys
import time

from openconvoy.comms.netns import run_in_netns
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.security.certs import PSID_BSM
from openconvoy.comms.tools import DEFAULT_SEND_ID


def test_listen_verifies_and_counts_per_sender(tmp_path):
    convoy = tmp_path / "lab.toml"
    convoy.write_text('[convoy]\nname = "lab"\n')
    keys, other = tmp_path / "lab.keys", tmp_path / "other.keys"
    now = time.time()
    for d, name in ((keys, "lab"), (other, "other")):
        ks.init_authority(d, name, now)
        ks.issue_vehicle(d, name, 1, now)
    # a frame the member signed 30 s ago, captured and replayed
    from openconvoy.comms import bsm as j

    old = Authenticator(ks.load_vehicle(keys, 1, now)).sign(
        j.encode_frame(j.BsmCore(0, DEFAULT_SEND_ID, 0, 286000000, -812000000, speed=0, heading=0)),
        PSID_BSM,
        now - 30.0,
    )
    cli = [sys.executable, "-m", "openconvoy.cli"]
    send = [*cli, "bsm", "send", "--iface", "oc0", "--count", "5", "--rate", "50", "--lat", "28.6",
            "--lon", "-81.2", "--speed", "2"]  # fmt: skip

    def after(delay_s: float, argv: list[str]) -> list[str]:
        # the listener must be listening first (interpreter start-up varies under load)
        return ["sh", "-c", f'sleep {delay_s}; exec "$@"', "sh", *argv]

    listen, member, forger, foreign, replay = run_in_netns(
        [
            [
                *cli,
                "bsm",
                "listen",
                "--iface",
                "oc0",
                "--convoy",
                str(convoy),
                "--count",
                "18",
                "--timeout",
                "40",
            ],
            after(3.0, [*send, "--key", str(keys / "vehicle-1.key")]),
            after(5.0, [*send, "--speed", "160"]),
            after(7.0, [*send, "--key", str(other / "vehicle-1.key")]),
            after(9.0, [*send, "--frame", old.hex(), "--count", "3"]),
        ],
        timeout=60,
    )
    for p in (member, forger, foreign, replay):
        assert p.returncode == 0, p.stderr
    assert listen.returncode == 0, listen.stderr
    lines = listen.stdout.strip().splitlines()
    accepted = [ln for ln in lines if ln.startswith("[lab.vehicle-1] id=")]
    assert len(accepted) == 5 and "speed=2.00 m/s" in accepted[0]
    summary = {ln.split(":")[0]: ln for ln in lines[-4:]}
    assert summary["lab.vehicle-1"] == "lab.vehicle-1: accepted 5, rejected 3 (stale=3)"
    unsigned = f"id {DEFAULT_SEND_ID.hex().upper()} (unsigned)"
    assert summary[unsigned] == f"{unsigned}: accepted 0, rejected 5 (unsigned=5)"
    foreign_line = next(v for k, v in summary.items() if k.startswith("digest "))
    # the first carries its certificate (not ours: bad), the rest only its digest
    assert foreign_line.endswith("accepted 0, rejected 5 (bad_certificate=5)")
    assert lines[-1] == "summary: 5 accepted, 13 rejected from 3 senders"
