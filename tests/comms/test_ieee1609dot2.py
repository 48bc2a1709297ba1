"""Our signed SPDUs and certificates against an independent IEEE 1609.2 decoder.

The independent decoder is pycrate's compilation of the published IEEE 1609.2 ASN.1
modules Ieee1609Dot2 and Ieee1609Dot2BaseTypes (``pycrate_asn1dir/ITS_IEEE1609_2.py``,
module OIDs {1 3 111 2 1609 2 1 1 2 3} and {... 2 1 2 2 2}), not our
``comms/security/ieee1609dot2.asn``. Compared: every field of the SPDU (version, content choice,
hashId, payload, headerInfo psid / generationTime / inlineP2pcdRequest, signer digest or
certificate, signature) and of both certificates (type, issuer, id name, cracaId,
crlSeries, validity, appPermissions, certIssuePermissions, verifyKeyIndicator,
signature); pycrate re-encodes each value to the same octets (canonical OER). The module
itself is compared type by type with the published one (components, optionality,
extension markers, ranges and sizes). Also two
SPDUs captured from a deployed roadside unit (a BSM and a SPaT, kept as test data by the
USDOT JPO ODE project) read the same with ours and pycrate's, and their generation times
confirm Time64's TAI epoch.
"""

from __future__ import annotations

import pytest
from auth_testdata import T0, creds
from hypothesis import given, settings
from hypothesis import strategies as st
from pycrate_asn1dir import ITS_IEEE1609_2 as M

from openconvoy.comms import bsm as j
from openconvoy.comms.security import certs as c
from openconvoy.comms.security import spdu as sp
from openconvoy.comms.security.auth import Authenticator


def _pycrate(type_name: str, module: str, data: bytes):
    t = getattr(getattr(M, module), type_name)
    t.from_oer(data)
    value = t.get_val()
    assert t.to_oer() == data  # canonical: pycrate writes the very same octets
    return value


@pytest.fixture(scope="module")
def frames() -> tuple[bytes, bytes, bytes]:
    core = j.BsmCore(7, b"\x4f\x43\x00\x01", 12345, 286024000, -812001000, speed=100, heading=7200)
    payload = j.encode_frame(core)
    a = Authenticator(creds(1))
    a._requests[b"\xaa\xbb\xcc"] = None  # as if we had heard an unknown digest
    with_cert = a.sign(payload, c.PSID_BSM, T0)
    with_digest = a.sign(payload, c.PSID_BSM, T0 + 0.1)
    return payload, with_cert, with_digest


def test_signed_bsm_decodes_identically_with_pycrate(frames):
    payload, with_cert, with_digest = frames
    cert = creds(1).certificate
    for data, signer in ((with_cert, "certificate"), (with_digest, "digest")):
        assert data[:2] == sp.SIGNED_PREFIX
        v = _pycrate("Ieee1609Dot2Data", "Ieee1609Dot2", data)
        assert v["protocolVersion"] == 3
        kind, sd = v["content"]
        assert kind == "signedData" and sd["hashId"] == "sha256"
        inner = sd["tbsData"]["payload"]["data"]
        assert inner == {"protocolVersion": 3, "content": ("unsecuredData", payload)}
        header = sd["tbsData"]["headerInfo"]
        ours = sp.decode_signed(data)
        assert header["psid"] == 0x20 == ours.psid
        assert header["generationTime"] == ours.generation_time
        assert (
            abs(
                c.unix_of_time64(ours.generation_time)
                - (T0 if signer == "certificate" else T0 + 0.1)
            )
            < 1e-6
        )
        sig_kind, sig = sd["signature"]
        assert sig_kind == "ecdsaNistP256Signature"
        assert sig["rSig"] == ("x-only", ours.r) and sig["sSig"] == ours.s
        assert sd["signer"][0] == signer
        if signer == "digest":
            assert sd["signer"][1] == cert.digest == ours.digest
            assert "inlineP2pcdRequest" not in header
        else:
            (pc,) = sd["signer"][1]
            assert M.Ieee1609Dot2.Certificate.from_oer(cert.coer) is None
            assert pc == M.Ieee1609Dot2.Certificate.get_val()
            assert header["inlineP2pcdRequest"] == [b"\xaa\xbb\xcc"]
        # the signature covers the tbsData octets pycrate finds
        tbs = M.Ieee1609Dot2.ToBeSignedData
        tbs.set_val(sd["tbsData"])
        assert tbs.to_oer() == ours.tbs
        assert c.verify(cert.public_key, ours.r, ours.s, ours.tbs, cert.coer)


def test_certificates_decode_identically_with_pycrate():
    cr = creds(2)
    for cert, issuer in (
        (cr.authority, ("self", "sha256")),
        (cr.certificate, ("sha256AndDigest", cr.authority.digest)),
    ):
        v = _pycrate("CertificateBase", "Ieee1609Dot2", cert.coer)
        assert v["version"] == 3 and v["type"] == "explicit"
        assert v["issuer"] == issuer
        tbs = v["toBeSigned"]
        assert tbs["id"] == ("name", cert.name)
        assert tbs["cracaId"] == b"\0\0\0" and tbs["crlSeries"] == 0
        assert tbs["validityPeriod"]["duration"][0] == "hours"
        assert abs(c.unix_of_time32(tbs["validityPeriod"]["start"]) - cert.valid_from) < 1
        assert {p["psid"] for p in tbs["appPermissions"]} == set(cert.psids)
        assert ("certIssuePermissions" in tbs) == cert.can_issue
        vk_kind, (alg, (point_kind, x)) = tbs["verifyKeyIndicator"]
        assert (vk_kind, alg) == ("verificationKey", "ecdsaNistP256")
        assert point_kind in ("compressed-y-0", "compressed-y-1")
        assert c.key_of_point((point_kind, x)).public_numbers() == cert.public_key.public_numbers()
        assert v["signature"] == c.signature_value(cert.r, cert.s)
        c.check_issued_by(cert, cr.authority, T0)


def test_pycrate_built_spdu_decodes_with_ours():
    # The other direction: an SPDU composed by pycrate from the published modules.
    cr = creds(0)
    payload = j.encode_frame(j.BsmCore(1, b"\x01\x02\x03\x04", 500, 0, 0, speed=0, heading=0))
    tbs_v = {
        "payload": {"data": {"protocolVersion": 3, "content": ("unsecuredData", payload)}},
        "headerInfo": {"psid": 32, "generationTime": c.time64(T0)},
    }
    tbs_t = M.Ieee1609Dot2.ToBeSignedData
    tbs_t.set_val(tbs_v)
    tbs = tbs_t.to_oer()
    r, s = c.sign(cr.key, tbs, cr.certificate.coer)
    d = M.Ieee1609Dot2.Ieee1609Dot2Data
    d.set_val(
        {
            "protocolVersion": 3,
            "content": (
                "signedData",
                {
                    "hashId": "sha256",
                    "tbsData": tbs_v,
                    "signer": ("digest", cr.certificate.digest),
                    "signature": ("ecdsaNistP256Signature", {"rSig": ("x-only", r), "sSig": s}),
                },
            ),
        }
    )
    ours = sp.decode_signed(d.to_oer())
    assert ours.payload == payload and ours.tbs == tbs and ours.digest == cr.certificate.digest
    assert c.verify(cr.certificate.public_key, ours.r, ours.s, ours.tbs, cr.certificate.coer)


@pytest.mark.parametrize("bad", [b"", b"\x03\x81", b"\x03\x81\x00\x40", bytes(range(256))[:90]])
def test_garbage_is_a_decode_error(bad):
    with pytest.raises(sp.SpduDecodeError):
        sp.decode_signed(b"\x03\x81" + bad)


def test_time64_is_tai_microseconds_since_2004():
    # 2004-01-01 00:00:00 UTC is 0 + the 5 leap seconds since.
    assert c.time64(1072915200.0) == 5_000_000
    assert c.unix_of_time64(c.time64(T0)) == pytest.approx(T0, abs=1e-6)


@settings(max_examples=150, deadline=None)
@given(
    payload=st.binary(min_size=0, max_size=300),
    psid=st.sampled_from([0x20, 0x7F, 0x80, 0x4000, c.PSID_ABORT]),
    t=st.floats(0, 1e9),
    request=st.booleans(),
    full=st.booleans(),
)
def test_the_direct_reading_equals_asn1tools(payload, psid, t, request, full):
    cr = creds(1)
    data = sp.encode_signed(
        payload,
        psid=psid,
        generation_time=c.time64(T0 + t),
        key=cr.key,
        certificate=cr.certificate,
        include_certificate=full,
        p2pcd_request=(b"abc",) if request else (),
    )
    slow = sp.decode_signed_asn1(data)
    assert sp.decode_signed(data) == slow
    assert (slow.payload, slow.psid, slow.generation_time) == (payload, psid, c.time64(T0 + t))
    assert c.verify(cr.certificate.public_key, slow.r, slow.s, slow.tbs, cr.certificate.coer)
    # the common layout is read directly: no header extension
    assert (sp._decode_common(data) is not None) == (not request)
    for cut in (len(data) - 1, len(data) // 2):
        with pytest.raises(sp.SpduDecodeError):
            sp.decode_signed(data[:cut])


# Two signed SPDUs captured from a roadside unit's traffic on 2023-05-03 and kept as test
# data by the USDOT JPO ODE project (Java package us.dot.its.jpo.ode.api.pcap, class
# PcapDecoderTests, UDP_FRAME and WSMP_FRAME): the SPDU octets start at "038100400380".
# (hex, psid, capture time: the pcap's frame.time_epoch, s)
CAPTURED = [
    (
        "038100400380630014604edee641a6f6c566d3144e145c1cb823de1d9415ba70005510fdfa1fa1007fff8000"
        "a02801009cc061002dbfcd500019b81002bbecb6ffc1fca0fe713456efde2ab20fe36af550fce334afffec80"
        "2107c0009000014e9b5fbfffc7ffff28000040012000022b029e7fa620807eee4644feddb2898080f9cc5b0e"
        "1fdf0341a83402f32ed81815bd20f6af31e46d907d255ab1e2bb544cf5420c3a91211db23249119980d24ed3"
        "5f0fea3270309d118328a129f52189f9",
        0x20,
        1683155397.59677,
    ),
    (
        "0381004003804d00134a42b3c30180c7ce400302b3c3dd6007001043425c1a5c1801021a130b530b400c10d0"
        "9dbe9dbe00808c84b014b45005043425c1a5c1803021a13155315401c10c095bc01008c84ae64b4450018200"
        "022b02ed6e026a18095de9bd6aaa9d38f6809127648f49b09c018082cad6384a78c2345441b13fd1c899e115"
        "9493bce677e94b0097749787def147bd4ecff7e31f436d5ba48358e391c4e8cfe9c96c036bcab2a3744cb5cb"
        "734e6d06",
        0x82,
        1683156721.857857,
    ),
]


@pytest.mark.parametrize("hex_, psid, t_capture", CAPTURED)
def test_captured_spdus_from_a_deployed_stack(hex_, psid, t_capture):
    data = bytes.fromhex(hex_)
    ours = sp.decode_signed(data)
    assert ours == sp.decode_signed_asn1(data)
    v = _pycrate("Ieee1609Dot2Data", "Ieee1609Dot2", data)
    sd = v["content"][1]
    assert sd["tbsData"]["headerInfo"]["psid"] == ours.psid == psid
    assert sd["tbsData"]["headerInfo"]["generationTime"] == ours.generation_time
    assert sd["signer"] == ("digest", ours.digest)
    assert sd["tbsData"]["payload"]["data"]["content"] == ("unsecuredData", ours.payload)
    sig_kind, sig = sd["signature"]
    assert sig_kind == "ecdsaNistP256Signature" and (sig["rSig"][1], sig["sSig"]) == (
        ours.r,
        ours.s,
    )
    # Time64 is TAI: generated ~0.1 s before it was captured only with the 5 leap seconds
    # (read as UTC it would be 5 s after the capture)
    assert 0.0 < t_capture - c.unix_of_time64(ours.generation_time) < 0.2
    if psid == 0x20:  # the BSM inside decodes with our J2735 codec
        bsm = j.decode_frame(ours.payload)
        assert bsm.part_ii_ids == (0, 2) and bsm.core.temp_id.hex() == "7b99069b"
        assert sp._decode_common(data) is not None  # the common layout, read directly
    else:  # a SPaT, generationLocation in its header, r as compressed-y-0: via asn1tools
        assert sig["rSig"][0] == "compressed-y-0"
        assert sp._decode_common(data) is None
        assert sd["tbsData"]["headerInfo"]["generationLocation"]["latitude"] == 403267049


def _published(name: str):
    for module in (M.Ieee1609Dot2, M.Ieee1609Dot2BaseTypes):
        t = getattr(module, name, None)
        if t is not None and hasattr(t, "TYPE"):
            return t
    return None


def test_our_module_restates_the_published_types_component_for_component():
    # Every SEQUENCE, CHOICE and ENUMERATED of comms/security/ieee1609dot2.asn that the published
    # modules define under the same name: the same root components in the same order,
    # the same OPTIONAL/DEFAULT ones, an extension marker where they have one, and only
    # a prefix of their extension additions (OER skips the ones left out).
    import asn1tools

    ours = asn1tools.parse_files(str(c.ASN_PATH))["OpenConvoyIeee1609Dot2"]["types"]
    compared = []
    for name, t in ours.items():
        pub = _published(name)
        if pub is None or t["type"] not in ("SEQUENCE", "CHOICE", "ENUMERATED"):
            continue
        assert pub.TYPE == t["type"], name
        if t["type"] == "ENUMERATED":
            names = [v[0] if isinstance(v, tuple) else v for v in t["values"]]
            root = names[: names.index(None)] if None in names else names
            ext = names[names.index(None) + 1 :] if None in names else None
            assert root == list(pub._root), name
        else:
            members = t["members"]
            cut = members.index(None) if None in members else len(members)
            root, ext_m = members[:cut], (members[cut + 1 :] if None in members else None)
            assert [m["name"] for m in root] == list(pub._root), name
            ext = None if ext_m is None else [m["name"] for m in ext_m if m is not None]
            if t["type"] == "SEQUENCE":
                for m in root:
                    p = pub._cont[m["name"]]
                    assert ("optional" in m or "default" in m) == bool(
                        p._opt or p._def is not None
                    ), (name, m["name"])
        assert (ext is None) == (pub._ext is None), name
        if ext is not None:
            assert ext == list(pub._ext)[: len(ext)], name
        compared.append(name)
    assert len(compared) >= 45, compared
    for must in (
        "Ieee1609Dot2Data",
        "SignedData",
        "ToBeSignedData",
        "HeaderInfo",
        "SignerIdentifier",
        "CertificateBase",
        "ToBeSignedCertificate",
        "EccP256CurvePoint",
        "Signature",
    ):
        assert must in compared


def test_our_integer_ranges_and_string_sizes_are_the_published_ones():
    import asn1tools

    ours = asn1tools.parse_files(str(c.ASN_PATH))["OpenConvoyIeee1609Dot2"]["types"]

    def bounds(const):
        out = []
        for x in const.root:
            if isinstance(x, int):
                out.append((x, x))
            else:
                out.append((x.lb, "MAX" if x.ub is None else x.ub))
        return out

    def ours_bounds(spec):
        return [v if isinstance(v, tuple) else (v, v) for v in spec]

    compared = 0
    for name, t in ours.items():
        pub = _published(name)
        if pub is None:
            continue
        if "restricted-to" in t:
            assert ours_bounds(t["restricted-to"]) == bounds(pub._const_val), name
            compared += 1
        if "size" in t:
            assert ours_bounds(t["size"]) == bounds(pub._const_sz), name
            compared += 1
    assert compared >= 20
