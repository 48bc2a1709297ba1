"""Authenticated V2V: signed BSMs through ``Sender``/``Receiver``, forgeries, replays
(with an injected clock), certificate learning and requests, signed and unsigned aborts."""

from __future__ import annotations

import pytest
from auth_testdata import T0, creds, keys_dir

from openconvoy.comms import bsm as j
from openconvoy.comms import legacy_json as cj
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.mapping import state_to_core
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig, Receiver, Sender
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)


def _state(i: int, t: float, x: float = 0.0) -> VehicleState:
    return VehicleState(i, t, x - 15.0 * i, 0.0, 1.0, 0.0)


def _pair(sender: int = 0, receiver: int = 1) -> tuple[Sender, Receiver]:
    tx = Sender(IDS, ORIGIN, sender, auth=Authenticator(creds(sender)))
    rx = Receiver(IDS, ORIGIN, receiver, auth=Authenticator(creds(receiver)))
    return tx, rx


def _frame(tx: Sender, t: float) -> bytes:
    out = tx.datagrams(_state(tx.vehicle_index, t, x=t - T0), t)
    assert out is not None
    return out[0]


def _rejected(rx: Receiver) -> dict[str, int]:
    return {k: v for k, v in rx.auth.counters.rejected.items() if v}


def test_signed_bsms_are_delivered_and_the_certificate_goes_out_once_a_second():
    tx, rx = _pair()
    frames = [_frame(tx, T0 + 0.1 * k) for k in range(25)]  # 2.5 s at 10 Hz
    with_cert = [k for k, f in enumerate(frames) if sp.decode_signed(f).certificate is not None]
    assert with_cert == [0, 10, 20]
    assert len(frames[1]) == len(frames[0]) - len(creds(0).certificate.coer) + 6
    for k, f in enumerate(frames):
        r = rx.handle(f, T0 + 0.1 * k + 0.02)
        assert r is not None and r.sender == 0 and r.state.x == pytest.approx(0.1 * k, abs=0.05)
    assert rx.counters.received == 25 and rx.counters.rejected == 0


def test_unknown_digest_is_dropped_asked_for_and_then_sent():
    tx, rx = _pair()
    _frame(tx, T0)  # the first one (with the certificate) was missed
    f = _frame(tx, T0 + 0.1)
    assert rx.handle(f, T0 + 0.12) is None and _rejected(rx) == {"unknown_signer": 1}
    # the receiver's next SPDU asks for it (inlineP2pcdRequest = the HashedId3) ...
    back = Sender(IDS, ORIGIN, 1, auth=rx.auth)
    request = _frame(back, T0 + 0.15)
    assert sp.decode_signed(request).p2pcd_request == (creds(0).certificate.digest[-3:],)
    # ... the sender hears it (and learns the receiver's certificate, sent in full first)
    sender_rx = Receiver(IDS, ORIGIN, 0, auth=tx.auth)
    assert sender_rx.handle(request, T0 + 0.16) is not None
    # ... and its next frame carries the full certificate, well before the 1 s period
    f2 = _frame(tx, T0 + 0.2)
    assert sp.decode_signed(f2).certificate == creds(0).certificate.coer
    assert rx.handle(f2, T0 + 0.22) is not None
    assert rx.handle(_frame(tx, T0 + 0.3), T0 + 0.32) is not None  # digest known now


def test_replays_at_half_a_second_a_minute_and_an_hour_are_rejected():
    tx, rx = _pair()
    captured = _frame(tx, T0)
    assert rx.handle(captured, T0 + 0.01) is not None
    # the same datagram again, the sender silent meanwhile: a duplicate
    assert rx.handle(captured, T0 + 0.5) is None
    # the sender went on at 10 Hz; the old frame replayed 0.5 s later: time and msgCnt went back
    for k in range(1, 5):
        assert rx.handle(_frame(tx, T0 + 0.1 * k), T0 + 0.1 * k + 0.01) is not None
    old = _frame(tx, T0 + 0.45)
    for k in range(5, 9):
        rx.handle(_frame(tx, T0 + 0.1 * k + 0.05), T0 + 0.1 * k + 0.06)
    assert rx.handle(old, T0 + 0.95) is None
    # a minute and an hour later: stale, whatever secMark says (it repeats every minute)
    assert rx.handle(captured, T0 + 60.0) is None
    assert rx.handle(captured, T0 + 3600.0) is None
    assert _rejected(rx) == {"duplicate": 1, "backwards": 1, "stale": 2}
    assert rx.counters.rejected == 4 and rx.counters.received == 9


def test_clock_stepping_back_with_msgcnt_going_on_is_not_a_replay():
    tx, rx = _pair()
    assert rx.handle(_frame(tx, T0), T0) is not None
    assert rx.handle(_frame(tx, T0 + 0.5), T0 + 0.5) is not None
    assert rx.handle(_frame(tx, T0 + 0.3), T0 + 0.6) is not None  # NTP stepped back 0.3 s
    assert rx.counters.rejected == 0


def test_future_and_configurable_window():
    tx = Sender(IDS, ORIGIN, 0, auth=Authenticator(creds(0)))
    rx = Receiver(IDS, ORIGIN, 1, auth=Authenticator(creds(1), window_s=5.0))
    assert rx.handle(_frame(tx, T0), T0 + 3.0) is not None  # 3 s old, window 5 s
    assert rx.handle(_frame(tx, T0 + 20.0), T0 + 4.0) is None
    assert _rejected(rx) == {"future": 1}


def test_forgeries_are_rejected_by_reason():
    _, rx = _pair()
    lead_core = state_to_core(_state(0, T0, x=1000.0), ORIGIN, IDS.id_of(0), 0)
    unsigned = j.encode_frame(lead_core)
    foreign = Authenticator(creds(0, convoy="other"))
    foreign_frame = foreign.sign(unsigned, c.PSID_BSM, T0)
    foreign_digest_only = foreign.sign(unsigned, c.PSID_BSM, T0 + 0.05)
    # vehicle 2 (a real member) claiming to be the leader
    impostor = Authenticator(creds(2)).sign(unsigned, c.PSID_BSM, T0)
    # a real leader frame with one payload bit flipped
    tx, _ = _pair()
    good = bytearray(_frame(tx, T0))
    good[40] ^= 0x01
    for data in (unsigned, foreign_digest_only, foreign_frame, impostor, bytes(good)):
        assert rx.handle(data, T0 + 0.02) is None
    assert _rejected(rx) == {
        "unsigned": 1,
        "bad_certificate": 1,
        "unknown_signer": 1,
        "wrong_sender": 1,
        "bad_signature": 1,
    }
    assert rx.counters.rejected == 5 and rx.counters.received == 0
    # a flood of the foreign certificate costs no more signature checks: remembered as bad
    assert rx.handle(foreign.sign(unsigned, c.PSID_BSM, T0 + 0.1), T0 + 0.12) is None
    assert rx.auth.counters.rejected["bad_certificate"] == 2


def test_own_signed_frames_are_echoes_and_garbage_is_malformed():
    tx, _ = _pair()
    own_rx = Receiver(IDS, ORIGIN, 0, auth=tx.auth)
    assert own_rx.handle(_frame(tx, T0), T0) is None and own_rx.counters.echoes == 1
    for junk in (b"\x03\x81", b"\x03\x81" + bytes(80), b"\x03\x81\xff" * 30):
        assert own_rx.handle(junk, T0) is None
    assert own_rx.counters.malformed == 3 and own_rx.counters.rejected == 0


def test_unsigned_abort_is_ignored_and_a_signed_one_is_obeyed():
    bus = MemoryBus()
    links = [
        V2V(
            LinkConfig("mem"),
            IDS,
            ORIGIN,
            i,
            transport=bus.endpoint(f"v{i}"),
            auth=Authenticator(creds(i)),
        )
        for i in range(3)
    ]
    bus.inject(cj.make_abort(T0), "operator")  # `openconvoy abort` without a key
    foreign = Authenticator(creds(0, convoy="other"))
    bus.inject(foreign.sign(cj.make_abort(T0), c.PSID_ABORT, T0), "intruder")
    for link in links:
        assert link.poll(T0 + 0.01) == []
        assert link.counters.aborts_rejected == 2 and link.counters.aborts == 0
    authority = ks.load_signer(keys_dir("lab") / "authority.key", creds(0).authority, T0)
    signed = Authenticator(authority).sign(cj.make_abort(T0), c.PSID_ABORT, T0 + 0.02)
    bus.inject(signed, "operator")
    for link in links:
        (r,) = link.poll(T0 + 0.03)
        assert r.abort and r.sender == -1 and r.state is None
    # a vehicle's key may not sign aborts (D63: only the authority or an operator key), and
    # the replayed operator's abort is not obeyed twice
    links[2].send_abort(T0 + 0.04)
    bus.inject(signed, "replay")
    for link in links[:2]:
        assert link.poll(T0 + 0.05) == []
        assert link.counters.aborts_rejected == 4
        (alert,) = link.take_alerts()
        assert "ignored an abort signed by lab.vehicle-2" in alert
    assert links[0].auth.counters.rejected["duplicate"] == 1
    assert links[0].auth.counters.rejected["not_permitted"] == 1


def test_compat_cannot_be_signed():
    with pytest.raises(ValueError, match="cannot be signed"):
        V2V(
            LinkConfig("mem", compat=True),
            IDS,
            ORIGIN,
            0,
            transport=MemoryBus().endpoint(),
            compat_transport=MemoryBus().endpoint(),
            auth=Authenticator(creds(0)),
        )


def test_without_auth_signed_frames_are_read_unverified():
    tx, _ = _pair()
    rx = Receiver(IDS, ORIGIN, 1)
    assert rx.handle(_frame(tx, T0), T0 + 0.01) is not None
