"""The plan message (comms.plans): codec, and the V2V link sending it beside the BSM,
signed under PSID_PLAN, over an in-memory bus; bad plan datagrams are counted, never raised."""

from __future__ import annotations

import random

import pytest
from auth_testdata import T0, creds
from hypothesis import given, settings
from hypothesis import strategies as st

from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import MemoryBus
from openconvoy.comms.plans import (
    PLAN_MAGIC,
    PlanDecodeError,
    decode_plan,
    encode_plan,
    peek_plan_id,
)
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator
from openconvoy.comms.security.certs import PSID_PLAN
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.core.plans import Plan
from openconvoy.core.state import VehicleState

ORIGIN = Origin(28.6024, -81.2001, 0.0)
IDS = TempIds("lab", 3)
ID1 = IDS.id_of(1)


def _plan(vid: int = 1, t0: float = T0, n: int = 21) -> Plan:
    return Plan(vid, t0, 0.1, tuple(1.0 + 0.05 * k for k in range(n)), 0.3)


@settings(max_examples=50, deadline=None)
@given(
    t0=st.floats(1.6e9, 2.0e9),
    step=st.sampled_from([0.05, 0.1, 0.2]),
    speeds=st.lists(st.floats(0.0, 60.0), min_size=1, max_size=64),
    tau=st.floats(0.0, 5.0),
)
def test_plans_round_trip_to_the_wire_resolution(t0, step, speeds, tau) -> None:
    plan = Plan(2, t0, step, tuple(speeds), tau)
    data = encode_plan(plan, ID1)
    assert data[:4] == PLAN_MAGIC and len(data) == 22 + 2 * len(speeds)
    assert peek_plan_id(data) == ID1
    temp_id, back = decode_plan(data, 2)
    assert temp_id == ID1 and back.vehicle_id == 2
    half_ms = 5e-4 + 1e-9  # the wire's 1 ms resolution: half a unit (a tie rounds to even)
    assert back.t0 == pytest.approx(t0, abs=half_ms)
    assert back.step_s == pytest.approx(step, abs=half_ms)
    assert back.tau_s == pytest.approx(tau, abs=half_ms)
    assert max(abs(a - b) for a, b in zip(back.speeds, speeds)) <= 0.01 + 1e-9


def test_bad_plan_bytes_are_decode_errors() -> None:
    good = encode_plan(_plan(), ID1)
    for bad, why in (
        (good[:10], "too short"),
        (b"XXXX" + good[4:], "magic"),
        (good[:4] + b"\x09" + good[5:], "version"),
        (good[:-1], "octets"),
        (good[:21] + b"\x00" + good[22:], "points"),
    ):
        with pytest.raises(PlanDecodeError, match=why):
            decode_plan(bad, 1)
    with pytest.raises(ValueError, match="valid"):
        encode_plan(Plan(1, T0, 0.1, (), 0.3), ID1)


def _links(auth: bool):
    bus = MemoryBus()
    out = []
    for i in range(3):
        a = Authenticator(creds(i)) if auth else None
        out.append(
            V2V(LinkConfig(iface="mem"), IDS, ORIGIN, i, transport=bus.endpoint(f"v{i}"), auth=a)
        )
    return out


@pytest.mark.parametrize("auth", [False, True])
def test_a_plan_goes_beside_the_bsm_and_arrives_as_sent(auth: bool) -> None:
    links = _links(auth)
    state = VehicleState(1, T0, -15.0, 0.0, 1.0, 0.0)
    assert links[1].send(state, T0) and links[1].send_plan(_plan(), T0)
    got = links[2].poll(T0 + 0.01)
    states = [r for r in got if r.state is not None]
    plans = [r for r in got if r.plan is not None]
    assert len(states) == 1 and len(plans) == 1
    p = plans[0]
    assert p.sender == 1 and p.plan is not None and p.plan.vehicle_id == 1
    assert p.plan.speeds[0] == pytest.approx(1.0) and p.plan.speeds[-1] == pytest.approx(2.0)
    c = links[2].counters
    assert (c.received, c.plans, c.malformed, c.rejected) == (2, 1, 0, 0)
    assert links[1].poll(T0 + 0.01) == [] and links[1].counters.echoes == 2


def test_signed_plans_are_spdus_under_their_own_psid_and_verified() -> None:
    bus = MemoryBus()
    rx = V2V(LinkConfig(iface="mem"), IDS, ORIGIN, 2, transport=bus.endpoint("rx"),
             auth=Authenticator(creds(2)))  # fmt: skip
    raw = bus.endpoint("tap")
    sender = Authenticator(creds(1))
    data = sender.sign(encode_plan(_plan(), ID1), PSID_PLAN, T0)
    assert data[:2] == sp.SIGNED_PREFIX and sp.decode_signed(data).psid == PSID_PLAN
    # vehicle 0's key signing vehicle 1's plan: it may only speak for itself
    forged = Authenticator(creds(0)).sign(encode_plan(_plan(), ID1), PSID_PLAN, T0)
    unsigned = encode_plan(_plan(), ID1)
    for d in (data, data, forged, unsigned):
        raw.send(d)
    got = rx.poll(T0 + 0.01)
    assert [r.sender for r in got] == [1]
    c = rx.counters
    assert (c.received, c.plans, c.rejected) == (1, 1, 3)  # replay, wrong sender, unsigned
    assert rx.auth is not None
    assert rx.auth.counters.rejected["wrong_sender"] == 1
    assert rx.auth.counters.rejected["unsigned"] == 1


def test_plan_datagram_fuzz_is_counted_and_never_raises() -> None:
    links = _links(False)
    good = encode_plan(_plan(), ID1)
    rnd = random.Random(5)
    raw = links[0]._tx
    n = 300
    for _ in range(n):
        b = bytearray(good)
        for _ in range(rnd.randint(1, 6)):
            b[rnd.randrange(len(b))] = rnd.randrange(256)
        raw.send(bytes(b[: rnd.randint(0, len(b))]))
    links[2].poll(T0)
    c = links[2].counters
    assert c.datagrams == n
    assert c.datagrams == (
        c.received + c.malformed + c.filtered + c.echoes + c.duplicates + c.rejected + c.lost
    )
