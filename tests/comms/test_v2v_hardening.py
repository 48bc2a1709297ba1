"""Issue 22's V2V side: replays of unsigned traffic (D46), message age and clock offsets
(D50), canonical and bounded certificates (D51, D55), revocation and position jumps (D53),
who may sign aborts and completions (D63, D62), disagreement about auth. Real ASN.1
(asn1tools), real ECDSA (cryptography); time is injected."""

from __future__ import annotations

import pytest
from auth_testdata import T0, creds, keys_dir

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import MAX_CERTS, Authenticator, Credentials
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig, Receiver, Sender, make_complete
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)


def _state(i: int, t: float, x: float = 0.0) -> VehicleState:
    return VehicleState(i, t, x - 15.0 * i, 0.0, 1.0, 0.0, 0.0, 0.0, 0.8, 0.3)


def _frame(tx: Sender, t: float, x: float = 0.0) -> bytes:
    out = tx.datagrams(_state(tx.vehicle_index, t, x), t)
    assert out is not None
    return out[0]


def _auth(i: int) -> Authenticator:
    return Authenticator(creds(i))


# --- D46: unsigned traffic ------------------------------------------------------------------


def test_an_unsigned_frame_replayed_a_minute_to_an_hour_later_is_not_fresh():
    # the defect's repro: the same unsigned frame handled again 60 s, 120 s and 1 h later
    # was delivered with age 0.05 s each time
    tx, rx = Sender(IDS, ORIGIN, 0), Receiver(IDS, ORIGIN, 1)
    f = _frame(tx, T0)
    assert rx.handle(f, T0 + 0.05).age == pytest.approx(0.05, abs=2e-3)
    for later in (60.0, 120.0, 3600.0):
        assert rx.handle(f, T0 + 0.05 + later) is None
    assert rx.counters.replays == 3
    # fresh frames of the same sender still go through
    assert rx.handle(_frame(tx, T0 + 3600.2, x=1.0), T0 + 3600.25) is not None


def test_members_that_disagree_about_auth_refuse_the_start():
    bus = MemoryBus()
    signed = V2V(LinkConfig("mem"), IDS, ORIGIN, 1, transport=bus.endpoint("1"), auth=_auth(1))
    unsigned = V2V(LinkConfig("mem"), IDS, ORIGIN, 2, transport=bus.endpoint("2"))
    leader = V2V(LinkConfig("mem"), IDS, ORIGIN, 0, transport=bus.endpoint("0"), auth=_auth(0))
    assert signed.start_refusal(T0) == ""
    unsigned.send(_state(2, T0), T0)
    leader.send(_state(0, T0), T0)
    assert signed.poll(T0 + 0.01)[0].sender == 0  # the signed leader is heard
    refusal = signed.start_refusal(T0 + 0.01)
    assert "vehicle 2 sends unsigned V2V messages while this vehicle requires signatures" in (
        refusal
    )
    assert unsigned.poll(T0 + 0.01)  # it reads the leader's payload unverified ...
    assert "vehicle 0 signs its V2V messages" in unsigned.start_refusal(T0 + 0.01)  # ... and says
    assert len(signed.take_alerts()) == 1 and signed.take_alerts() == []


# --- D50: age and clock offsets -------------------------------------------------------------


def test_a_sender_clock_ahead_within_the_tolerance_reads_as_fresh_not_a_minute_old():
    # the defect's repro: a sender 0.8 s ahead gave age 59.2 s
    T = 1.8e9
    f = _frame(Sender(IDS, ORIGIN, 0), T + 0.8)
    r = Receiver(IDS, ORIGIN, 1).handle(f, T)
    assert r is not None and r.age == 0.0


def test_signed_age_comes_from_the_generation_time_and_the_offset_is_measured():
    bus = MemoryBus()
    leader = V2V(LinkConfig("mem"), IDS, ORIGIN, 0, transport=bus.endpoint("0"), auth=_auth(0))
    rx = V2V(LinkConfig("mem"), IDS, ORIGIN, 1, transport=bus.endpoint("1"), auth=_auth(1))
    # the leader's clock 0.3 s behind ours: a 0.32 s age, read from the signed time
    leader.send(_state(0, T0 - 0.3), T0 - 0.3)
    (r,) = rx.poll(T0 + 0.02)
    assert r.age == pytest.approx(0.32, abs=1e-3)
    assert rx.clock_offsets(T0 + 0.02)[0] == pytest.approx(-0.32, abs=1e-3)
    assert rx.start_refusal(T0 + 0.02) == ""
    # 0.8 s ahead: age 0 (within the 1 s tolerance), offset named
    leader.send(_state(0, T0 + 1.8), T0 + 1.8)
    (r,) = rx.poll(T0 + 1.0)
    assert r.age == 0.0 and rx.clock_offsets(T0 + 1.0)[0] == pytest.approx(0.8, abs=1e-3)
    assert rx.start_refusal(T0 + 1.0) == ""
    # over half the tolerance: named in one line, once a minute
    assert rx.take_alerts() == [
        "vehicle 1: vehicle 0's clock is 0.80 s ahead of this vehicle's (tolerance 1 s)"
    ]
    assert rx.take_alerts(T0 + 30.0) == []


def test_a_clock_beyond_the_tolerance_is_named_and_refuses_the_start():
    bus = MemoryBus()
    leader = V2V(LinkConfig("mem"), IDS, ORIGIN, 0, transport=bus.endpoint("0"), auth=_auth(0))
    rx = V2V(LinkConfig("mem"), IDS, ORIGIN, 1, transport=bus.endpoint("1"), auth=_auth(1))
    for k in range(40):  # 2 s ahead: every message is "future", yet the offset is known
        t = T0 + 0.05 * k
        leader.send(_state(0, t + 2.0), t + 2.0)
        assert rx.poll(t + 0.01) == []
    assert rx.auth.counters.rejected["future"] == 40
    refusal = rx.start_refusal(T0 + 2.0)
    assert "vehicle 0's clock is 1.99 s ahead of this vehicle's" in refusal
    assert "1 s tolerance" in refusal
    # measured by verifying at most one such message a second (a flood of them is cheap)
    assert rx.auth.counters.rejected["bad_signature"] == 0
    # unsigned: the secMark gives the offset too (here 2 s behind)
    tx, plain = (
        Sender(IDS, ORIGIN, 2),
        V2V(LinkConfig("mem"), IDS, ORIGIN, 1, transport=bus.endpoint("p")),
    )
    f = _frame(tx, T0 - 2.0)
    plain.receiver.handle(f, T0)
    assert "vehicle 2's clock is 2.00 s behind" in plain.start_refusal(T0)


def test_the_link_tolerance_is_the_convoy_replay_window():
    from openconvoy.convoy import V2VConfig

    cfg = LinkConfig.from_v2v(V2VConfig(replay_window_s=2.5), "wlan0")
    assert cfg.time_tolerance_s == 2.5


# --- D51, D55: certificates -----------------------------------------------------------------


def _with_certificate(i: int, t: float) -> bytes:
    cr = creds(i)
    payload = j.encode_frame(
        __import__("openconvoy.comms.mapping", fromlist=["x"]).state_to_core(
            _state(i, t), ORIGIN, IDS.id_of(i), 0
        ),
        check=False,
    )
    return sp.encode_signed(
        payload,
        psid=c.PSID_BSM,
        generation_time=c.time64(t),
        key=cr.key,
        certificate=cr.certificate,
        include_certificate=True,
    )


def test_certificate_variants_are_rejected_and_the_cache_stays_bounded():
    spdu = _with_certificate(0, T0)
    n_cert = len(creds(0).certificate.coer)
    end = len(spdu) - 66  # the certificate ends where the signature starts
    assert spdu[end - n_cert : end] == creds(0).certificate.coer
    rx = Receiver(IDS, ORIGIN, 1, auth=_auth(1))
    for k in range(2000):  # 4 octets inserted after the certificate, 2000 ways
        variant = spdu[:end] + k.to_bytes(4, "big") + spdu[end:]
        assert rx.handle(variant, T0 + 0.01) is None
    a = rx.auth
    assert a.counters.certificates_learned == 0
    assert a.counters.rejected["bad_certificate"] == 2000
    assert a.certificates_cached == 2  # the authority's and our own, nothing else
    assert rx.handle(spdu, T0 + 0.01) is not None  # the genuine one still works
    # a certificate file that is not canonical OER is refused too
    with pytest.raises(c.CertificateError, match="not canonical"):
        c.parse_certificate(creds(0).certificate.coer + b"\x00")


def test_the_certificate_cache_is_bounded_lru():
    cr = creds(1)
    authority_key = ks.load_authority(keys_dir("lab"), with_key=True)[1]
    a = Authenticator(cr)
    for k in range(MAX_CERTS + 20):
        key = __import__("cryptography.hazmat.primitives.asymmetric.ec", fromlist=["ec"])
        priv = key.generate_private_key(key.SECP256R1())
        cert = c.make_certificate(
            f"lab.vehicle-{k + 3}",
            priv.public_key(),
            psids=(c.PSID_BSM,),
            start_unix=T0 - 60,
            duration_hours=1,
            issuer=(cr.authority, authority_key),
        )
        payload = b"\x00\x14" + bytes(30)
        spdu = sp.decode_signed(
            sp.encode_signed(
                payload,
                psid=c.PSID_BSM,
                generation_time=c.time64(T0 + k * 1e-3),
                key=priv,
                certificate=cert,
                include_certificate=True,
            )
        )
        assert a.check(spdu, T0 + k * 1e-3) == cert
    assert a.counters.certificates_learned == MAX_CERTS + 20
    assert a.certificates_cached == MAX_CERTS + 2


def test_a_certificate_with_an_unknown_choice_is_a_decode_error_not_an_escape():
    spdu = _with_certificate(1, T0)
    cert_at = spdu.index(creds(1).certificate.coer)
    id_tag = cert_at + creds(1).certificate.coer.index(b"\x81\x0dlab.vehicle-1")
    bad = spdu[:id_tag] + b"\x8f" + spdu[id_tag + 1 :]  # toBeSigned.id: an unknown CHOICE
    with pytest.raises(sp.SpduDecodeError, match="cannot be re-encoded"):
        sp.decode_signed_asn1(bad)
    rx = Receiver(IDS, ORIGIN, 0, auth=_auth(0))
    assert rx.handle(bad, T0 + 0.01) is None
    assert rx.counters.malformed + rx.counters.rejected == 1
    assert rx.auth.counters.rejected["bad_certificate"] + rx.counters.malformed == 1


# --- D53, D63: revocation, jumps, impersonation, aborts, completions --------------------------


def test_a_revoked_certificate_is_refused():
    old = creds(1)
    revoked = Credentials(
        creds(2).authority, creds(2).certificate, creds(2).key, frozenset({old.certificate.digest})
    )
    rx = Receiver(IDS, ORIGIN, 2, auth=Authenticator(revoked))
    tx = Sender(IDS, ORIGIN, 1, auth=Authenticator(old))
    assert rx.handle(_frame(tx, T0), T0 + 0.01) is None
    assert rx.auth.counters.rejected["revoked"] == 1


def test_two_position_streams_under_one_identity_are_flagged():
    bus = MemoryBus()
    rx = V2V(LinkConfig("mem"), IDS, ORIGIN, 2, transport=bus.endpoint("2"), auth=_auth(2))
    genuine = Sender(IDS, ORIGIN, 1, auth=Authenticator(creds(1)))
    for k in range(10):
        t = T0 + 0.05 * k
        bus.inject(_frame(genuine, t, x=0.05 * k), "v1")
        bus.inject(_frame(genuine, t + 0.01, x=40.0 + 0.05 * k), "thief")  # stolen key, 40 m on
        rx.poll(t + 0.02)
    assert rx.receiver._jumps.jumps[1] == 19
    (alert,) = rx.take_alerts()
    assert "vehicle 1's position jumped 40.0 m in 0.01 s" in alert and "keys issue" in alert
    assert rx.metadata["position_jumps"] == {1: 19}


def test_a_bsm_signed_with_our_temp_id_by_another_member_is_flagged():
    # D63: vehicle 1's key signs a BSM carrying the leader's temp id
    leader = Receiver(IDS, ORIGIN, 0, auth=_auth(0))
    forged_state = _state(0, T0)
    core = __import__("openconvoy.comms.mapping", fromlist=["x"]).state_to_core(
        forged_state, ORIGIN, IDS.id_of(0), 5
    )
    frame = Authenticator(creds(1)).sign(j.encode_frame(core, check=False), c.PSID_BSM, T0)
    assert leader.handle(frame, T0 + 0.01) is None
    assert leader.counters.impersonations == 1 and leader.counters.echoes == 0
    (alert,) = leader.alerts.take()
    assert "lab.vehicle-1 signs BSMs with this vehicle's temp id" in alert


def test_the_leader_signs_its_completion_and_nobody_else_can():
    bus = MemoryBus()
    links = [
        V2V(LinkConfig("mem"), IDS, ORIGIN, i, transport=bus.endpoint(str(i)), auth=_auth(i))
        for i in range(3)
    ]
    links[0].send_complete(T0)
    for link in links[1:]:
        got = link.poll(T0 + 0.01)
        assert [(r.complete, r.sender, r.state) for r in got] == [(True, 0, None)] * 3
    # vehicle 1 saying the scenario is complete: its certificate may not (D62/D63)
    links[1].send_complete(T0 + 0.1)
    assert links[2].poll(T0 + 0.11) == []
    assert links[2].auth.counters.rejected["not_permitted"] == 3
    # unsigned (auth = "off"): delivered once, a replay is not
    rx = Receiver(IDS, ORIGIN, 1)
    data = make_complete(T0, 0)
    assert rx.handle(data, T0).complete and rx.handle(data, T0 + 60) is None
    # an unsigned completion is nothing to a verifying vehicle
    assert links[1].receiver.handle(data, T0) is None


def test_an_abort_signed_by_a_vehicle_certificate_allowing_aborts_is_ignored():
    # certificates issued before issue 22 let vehicles sign aborts: still not obeyed
    cr = creds(1)
    authority_key = ks.load_authority(keys_dir("lab"), with_key=True)[1]
    old_style = c.make_certificate(
        "lab.vehicle-1",
        cr.key.public_key(),
        psids=(c.PSID_BSM, c.PSID_ABORT),
        start_unix=T0 - 60,
        duration_hours=1,
        issuer=(cr.authority, authority_key),
    )
    signer = Authenticator(Credentials(cr.authority, old_style, cr.key))
    rx = Receiver(IDS, ORIGIN, 2, auth=_auth(2))
    assert rx.handle(signer.sign(cj.make_abort(T0), c.PSID_ABORT, T0), T0 + 0.01) is None
    assert rx.counters.aborts == 0 and rx.counters.aborts_rejected == 1
    assert "ignored an abort signed by lab.vehicle-1" in rx.alerts.take()[0]
