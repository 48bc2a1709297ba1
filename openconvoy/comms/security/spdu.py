"""Signed IEEE 1609.2 SPDUs: ``Ieee1609Dot2Data`` with ``signedData`` around a payload.

On the wire (canonical OER, ``ieee1609dot2.asn``)::

    Ieee1609Dot2Data { protocolVersion 3, content signedData: SignedData {
        hashId sha256,
        tbsData { payload { data: Ieee1609Dot2Data { 3, unsecuredData: <payload> } },
                  headerInfo { psid, generationTime, [inlineP2pcdRequest] } },
        signer digest: HashedId8 | certificate: { <the signer's certificate> },
        signature ecdsaNistP256Signature { rSig x-only, sSig } } }

The payload of a BSM SPDU (PSID 0x20) is the unsecured UPER J2735 MessageFrame, as
deployed V2X stacks send it. Every SPDU starts ``03 81`` (version 3, choice signedData).

``encode_signed`` builds one; ``decode_signed`` parses one and locates the to-be-signed
octets inside the datagram (what the signature covers), without checking the signature:
``security.auth`` does that with the signer's certificate.

Most SPDUs on a convoy's link have one layout (a header of PSID and generation time only,
a digest or one certificate as signer, an x-only r): ``decode_signed`` reads those octet
by octet, and everything else through asn1tools. Reading them with asn1tools cost as much as the ECDSA verification;
tests/comms/test_ieee1609dot2.py holds both readings equal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ec

from openconvoy.comms.security import certs as c

#: Every signed SPDU starts with these octets: protocolVersion 3, content = signedData.
SIGNED_PREFIX = b"\x03\x81"
#: Octets before tbsData: the two above and hashId (sha256 = 0).
_TBS_OFFSET = 3


class SpduDecodeError(ValueError):
    """Not a signed IEEE 1609.2 SPDU we can read (message says why)."""


@dataclass(frozen=True, slots=True)
class SignedSpdu:
    """A parsed signed SPDU (signature not yet checked).

    Attributes:
        psid: headerInfo.psid.
        generation_time: headerInfo.generationTime, 1609.2 Time64 (TAI µs since 2004).
        payload: the unsecured data inside (for a BSM: the J2735 MessageFrame).
        digest: the signer's certificate HashedId8 (computed when the certificate is sent).
        certificate: the signer's certificate COER when sent in full, else None.
        certificate_value: its decoded value when asn1tools read the SPDU (else None).
        tbs: the to-be-signed octets (COER of tbsData) as they are in the datagram.
        r, s: the signature.
        p2pcd_request: HashedId3s of certificates the sender asks for (inlineP2pcdRequest).
    """

    psid: int
    generation_time: int
    payload: bytes
    digest: bytes
    certificate: bytes | None
    certificate_value: dict[str, Any] | None = field(compare=False)
    tbs: bytes
    r: bytes
    s: bytes
    p2pcd_request: tuple[bytes, ...] = ()


def encode_signed(
    payload: bytes,
    *,
    psid: int,
    generation_time: int,
    key: ec.EllipticCurvePrivateKey,
    certificate: c.Certificate,
    include_certificate: bool,
    p2pcd_request: tuple[bytes, ...] = (),
) -> bytes:
    """A signed SPDU carrying ``payload``, signed by ``key`` (whose certificate is
    ``certificate``), identified by the certificate's digest or, with
    ``include_certificate``, the certificate itself. ``p2pcd_request``: HashedId3s of
    certificates this sender asks their holders to send (unknown digests it heard)."""
    spec = c.spec()
    header: dict[str, Any] = {"psid": psid, "generationTime": generation_time}
    if p2pcd_request:
        header["inlineP2pcdRequest"] = list(p2pcd_request)
    tbs_value = {
        "payload": {"data": {"protocolVersion": 3, "content": ("unsecuredData", payload)}},
        "headerInfo": header,
    }
    tbs = spec.encode("ToBeSignedData", tbs_value)
    # A self-signed signer (the authority) hashes the empty string as its signer input
    # only for its own certificate; signing data, every signer hashes its certificate.
    r, s = c.sign(key, tbs, certificate.coer)
    if include_certificate:
        signer = b"\x81\x01\x01" + certificate.coer  # certificate: SEQUENCE OF, quantity 1
    else:
        signer = b"\x80" + certificate.digest
    # rSig x-only (choice 0), sSig: the fixed 66-octet ecdsaNistP256Signature.
    return SIGNED_PREFIX + b"\x00" + tbs + signer + b"\x80\x80" + r + s


def _oer_length(data: bytes, i: int) -> tuple[int, int]:
    """(length, index after it) of the OER length determinant at ``data[i]``."""
    b = data[i]
    if b < 0x80:
        return b, i + 1
    n = b & 0x7F
    if not 0 < n <= 3:
        raise IndexError("unsupported length determinant")
    return int.from_bytes(data[i + 1 : i + 1 + n], "big"), i + 1 + n


# Octets of the common layout: version 3, signedData, sha256, payload preamble (data
# present), inner Ieee1609Dot2Data version 3 with unsecuredData.
_FAST_HEAD = b"\x03\x81\x00\x40\x03\x80"
_HEADER_PSID_TIME = 0x40  # HeaderInfo preamble: no extensions, generationTime only
_DIGEST_AND_SIG = b"\x80"  # signer digest; the signature then starts 80 80 (x-only r)


def _decode_common(data: bytes) -> SignedSpdu | None:
    """The common layout read directly, or None (then asn1tools reads it)."""
    if data[:6] != _FAST_HEAD:
        return None
    try:
        n, p = _oer_length(data, 6)
        q = p + n
        if data[q] != _HEADER_PSID_TIME:
            return None
        psid_len = data[q + 1]
        g = q + 2 + psid_len
        end = g + 8  # end of tbsData
        sig = len(data) - 66  # the signature: 80 80 (x-only r), r, s
        if data[sig : sig + 2] != b"\x80\x80" or not 0 < psid_len <= 4:
            return None
        if data[end] == 0x80 and sig == end + 9:  # signer: digest
            cert, digest = None, data[end + 1 : sig]
        elif data[end : end + 3] == b"\x81\x01\x01" and sig > end + 3:  # one certificate
            # whatever it holds, the certificate is what lies between; a verifier that
            # does not know its digest yet parses it (auth)
            cert = data[end + 3 : sig]
            digest = c.hashed_id8(cert)
        else:
            return None
    except IndexError:
        return None
    return SignedSpdu(
        psid=int.from_bytes(data[q + 2 : g], "big"),
        generation_time=int.from_bytes(data[g:end], "big"),
        payload=data[p:q],
        digest=digest,
        certificate=cert,
        certificate_value=None,
        tbs=data[_TBS_OFFSET:end],
        r=data[sig + 2 : sig + 34],
        s=data[sig + 34 :],
    )


def decode_signed(data: bytes) -> SignedSpdu:
    """Parse a signed SPDU; ``SpduDecodeError`` unless it is one carrying unsecured data
    with a PSID and a generation time, signed with ECDSA P-256 by a digest or one
    explicit certificate."""
    if data[:2] != SIGNED_PREFIX:
        raise SpduDecodeError("not a signed IEEE 1609.2 SPDU (does not start 03 81)")
    common = _decode_common(data)
    if common is not None:
        return common
    return decode_signed_asn1(data)


def decode_signed_asn1(data: bytes) -> SignedSpdu:
    """``decode_signed`` entirely through asn1tools (any layout); only ever raises
    ``SpduDecodeError``."""
    try:
        return _decode_signed_asn1(data)
    except SpduDecodeError:
        raise
    except Exception as exc:  # a shape we did not expect (e.g. content not signedData)
        raise SpduDecodeError(f"not a signed SPDU we can read: {type(exc).__name__}") from None


def _decode_signed_asn1(data: bytes) -> SignedSpdu:
    if data[:2] != SIGNED_PREFIX:
        raise SpduDecodeError("not a signed IEEE 1609.2 SPDU (does not start 03 81)")
    try:
        v = c.spec().decode("Ieee1609Dot2Data", data)
    except Exception as exc:  # asn1tools raises many types on garbage; all mean "invalid"
        raise SpduDecodeError(f"invalid OER: {type(exc).__name__}: {exc}") from None
    sd = v["content"][1]
    if sd["hashId"] != "sha256":
        raise SpduDecodeError(f"hash algorithm {sd['hashId']}")
    tbs_v = sd["tbsData"]
    inner = tbs_v["payload"].get("data")
    if inner is None or inner["content"][0] != "unsecuredData":
        raise SpduDecodeError("payload is not unsecured data")
    header = tbs_v["headerInfo"]
    gen = header.get("generationTime")
    if gen is None:
        raise SpduDecodeError("no generation time")
    try:
        r, s = c.signature_parts(sd["signature"])
    except c.CertificateError as exc:
        raise SpduDecodeError(str(exc)) from None
    sig_len = 66
    end, digest, cert_bytes, cert_value = _signer_span(data, sd["signer"], sig_len)
    if end <= _TBS_OFFSET or len(data) - end - sig_len < 0:
        raise SpduDecodeError("truncated")
    return SignedSpdu(
        psid=header["psid"],
        generation_time=gen,
        payload=bytes(inner["content"][1]),
        digest=digest,
        certificate=cert_bytes,
        certificate_value=cert_value,
        tbs=data[_TBS_OFFSET:end],
        r=r,
        s=s,
        p2pcd_request=tuple(bytes(h) for h in header.get("inlineP2pcdRequest", ())),
    )


def _signer_span(
    data: bytes, signer_choice: tuple[str, Any], sig_len: int
) -> tuple[int, bytes, bytes | None, dict[str, Any] | None]:
    """Where the signed tbsData ends in ``data`` (the signer begins there), the signer's
    digest, and its certificate (OER bytes and value) when it is one; the SPDU must be
    canonical OER. The signer is a digest (1 + 8 octets) or one certificate (1 + 2 + its
    length), followed by the ``sig_len``-octet signature (1 + 33 + 32: x-only or
    compressed r)."""
    signer_kind, signer = signer_choice
    if signer_kind == "digest":
        digest = bytes(signer)
        end = len(data) - sig_len - 9
        if data[end : end + 9] != b"\x80" + digest:
            raise SpduDecodeError("trailing octets after the signature")
        return end, digest, None, None
    if signer_kind != "certificate":
        raise SpduDecodeError(f"signer is {signer_kind}")
    if len(signer) != 1:
        raise SpduDecodeError(f"signer is a chain of {len(signer)} certificates, expected 1")
    cert_value = signer[0]
    try:
        cert_bytes = c.spec().encode("CertificateBase", cert_value)
    except Exception as exc:  # an unknown CHOICE or enumeration value decodes, not encodes
        raise SpduDecodeError(f"signer certificate cannot be re-encoded: {exc}") from None
    end = len(data) - sig_len - 3 - len(cert_bytes)
    if data[end : end + 3] != b"\x81\x01\x01" or data[end + 3 : len(data) - sig_len] != cert_bytes:
        raise SpduDecodeError("signer certificate is not canonical OER")
    return end, c.hashed_id8(cert_bytes), cert_bytes, cert_value


def is_signed(data: bytes) -> bool:
    """Whether ``data`` looks like a signed SPDU (prefix only)."""
    return data[:2] == SIGNED_PREFIX
