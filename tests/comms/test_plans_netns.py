"""A plan message round-trips through the signed V2V path in a private network namespace
(IPv6 multicast on a veth pair), beside the BSMs, and a foreign IEEE 1609.2 decoder
(pycrate's compilation of the published ASN.1) still reads those BSMs: each is an SPDU
under the BSM's PSID whose payload is the J2735 frame; the plans are SPDUs under their
own PSID, which a BSM consumer passes over."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
from pycrate_asn1dir import ITS_IEEE1609_2 as M

from openconvoy.comms import bsm as j
from openconvoy.comms.netns import run_in_netns
from openconvoy.comms.plans import decode_plan
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security.certs import PSID_BSM, PSID_PLAN

PEER = Path(__file__).with_name("plan_peer.py")
ROUNDS = 8


@pytest.mark.netns
def test_signed_plans_round_trip_beside_bsms_that_foreign_decoders_read(tmp_path):
    keys = tmp_path / "lab.keys"
    now = time.time()
    ks.init_authority(keys, "lab", now)
    for i in range(3):
        ks.issue_vehicle(keys, "lab", i, now)
    (peer,) = run_in_netns([[sys.executable, str(PEER), str(keys), str(ROUNDS)]], timeout=60)
    assert peer.returncode == 0, peer.stderr
    out = json.loads(peer.stdout)
    # vehicle 2's verifying link: every BSM and every plan, nothing rejected
    assert out["counters"] == {"received": 2 * ROUNDS, "plans": ROUNDS, "rejected": 0,
                               "malformed": 0}  # fmt: skip
    assert [s["speed"] for s in out["states"]] == [2.0] * ROUNDS
    first = out["plans"][0]
    assert first["sender"] == 1 and len(first["speeds"]) == 21
    assert first["speeds"][0] == pytest.approx(2.0) and first["speeds"][-1] == pytest.approx(4.0)
    # the foreign decoder on the raw datagrams
    psids = {PSID_BSM: 0, PSID_PLAN: 0}
    for hexdata in out["raw"]:
        data = bytes.fromhex(hexdata)
        t = M.Ieee1609Dot2.Ieee1609Dot2Data
        t.from_oer(data)
        kind, sd = t.get_val()["content"]
        assert kind == "signedData"
        psid = sd["tbsData"]["headerInfo"]["psid"]
        payload = sd["tbsData"]["payload"]["data"]["content"][1]
        psids[psid] += 1
        if psid == PSID_BSM:
            assert payload[:2] == j.BSM_FRAME_PREFIX
            assert j.decode_frame(payload).core.speed == 100  # 2 m/s in 0.02 m/s units
        else:
            assert psid == PSID_PLAN and payload[:2] != j.BSM_FRAME_PREFIX
            assert decode_plan(payload, 1)[1].speeds[-1] == pytest.approx(4.0)
    assert psids == {PSID_BSM: ROUNDS, PSID_PLAN: ROUNDS}
