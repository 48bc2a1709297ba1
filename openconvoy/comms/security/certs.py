"""IEEE 1609.2 explicit certificates and ECDSA NIST P-256 signatures for the convoy.

A convoy has one authority (a self-signed root certificate, ``issuer = self``) that issues
one certificate per vehicle (``issuer = sha256AndDigest`` of the authority's). Each
certificate names its holder (``id.name``: ``<convoy>.authority``, ``<convoy>.vehicle-<N>``),
lists the PSIDs it may sign for (``appPermissions``) and carries the holder's public key
as a compressed P-256 point. The types are those of ``ieee1609dot2.asn`` (canonical OER).

Signatures follow IEEE 1609.2 (5.3.1): ECDSA-SHA-256 over ``SHA-256(to-be-signed COER) ||
SHA-256(signer's certificate COER)`` (the second hash is of the empty string for a
self-signed certificate), with ``r`` sent as an x-only point and ``s`` as 32 octets.
A certificate's ``HashedId8`` is the low-order (last) 8 octets of SHA-256 of its COER
encoding; its ``HashedId3`` the last 3.

Keys come from the ``cryptography`` package (OpenSSL). No I/O here: ``security.keystore`` reads
and writes the files.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import (
    decode_dss_signature,
    encode_dss_signature,
)

from openconvoy.core.errors import ConfigError, InputFileError

ASN_PATH = Path(__file__).with_name("ieee1609dot2.asn")

#: PSID of the BSM (IEEE 1609.12).
PSID_BSM = 0x20
#: PSID of OpenConvoy's convoy-wide abort. Not an IEEE-assigned value: picked from the
#: 4-octet p-encoded range (0xE0000000..), where no public allocation exists.
PSID_ABORT = 0xE0004F43
#: PSID of the leader's "scenario complete" (``comms.v2v``): the next value of that range.
PSID_COMPLETE = 0xE0004F44
#: PSID of OpenConvoy's plan message (``comms.plans``: a speed forecast beside the BSM, as
#: SAE J2945/6's cooperative control messages carry). From the same private range.
PSID_PLAN = 0xE0004F50

#: 1609.2 times count TAI seconds from 2004-01-01 00:00:00 UTC; TAI ran 5 s ahead of UTC's
#: count since then (leap seconds of 2005, 2008, 2012, 2015, 2016).
EPOCH_2004_UNIX = 1072915200
LEAP_SECONDS_SINCE_2004 = 5

_CURVE = ec.SECP256R1()
_ECDSA = ec.ECDSA(hashes.SHA256())
_EMPTY_HASH = hashlib.sha256(b"").digest()
_ORDER = 0xFFFFFFFF00000000FFFFFFFFFFFFFFFFBCE6FAADA7179E84F3B9CAC2FC632551  # of P-256


class CertificateError(InputFileError):
    """A certificate is malformed, not issued by the expected authority, or not valid."""


@functools.cache
def spec() -> Any:
    """The compiled 1609.2 subset (asn1tools, OER), once per process."""
    import asn1tools

    return asn1tools.compile_files(str(ASN_PATH), "oer")


def time64(unix_s: float) -> int:
    """1609.2 ``Time64`` (TAI microseconds since 2004) of a Unix time in seconds."""
    return int(round((unix_s - EPOCH_2004_UNIX + LEAP_SECONDS_SINCE_2004) * 1e6))


def unix_of_time64(t64: int) -> float:
    """Unix time (s) of a 1609.2 ``Time64``."""
    return t64 / 1e6 + EPOCH_2004_UNIX - LEAP_SECONDS_SINCE_2004


def time32(unix_s: float) -> int:
    """1609.2 ``Time32`` (TAI seconds since 2004) of a Unix time in seconds."""
    return int(unix_s - EPOCH_2004_UNIX + LEAP_SECONDS_SINCE_2004)


def unix_of_time32(t32: int) -> float:
    return float(t32 + EPOCH_2004_UNIX - LEAP_SECONDS_SINCE_2004)


def hashed_id8(cert_coer: bytes) -> bytes:
    """HashedId8 of a certificate: the last 8 octets of SHA-256 of its COER encoding."""
    return hashlib.sha256(cert_coer).digest()[-8:]


def hashed_id3(cert_coer: bytes) -> bytes:
    """HashedId3 of a certificate (the last 3 octets of its SHA-256; of its HashedId8)."""
    return hashlib.sha256(cert_coer).digest()[-3:]


def signing_input(tbs: bytes, signer_cert: bytes | None) -> bytes:
    """What ECDSA-SHA-256 signs: ``SHA-256(tbs) || SHA-256(signer certificate or b"")``."""
    signer_hash = _EMPTY_HASH if signer_cert is None else hashlib.sha256(signer_cert).digest()
    return hashlib.sha256(tbs).digest() + signer_hash


def sign(
    key: ec.EllipticCurvePrivateKey, tbs: bytes, signer_cert: bytes | None
) -> tuple[bytes, bytes]:
    """(r, s), 32 octets each, of ``tbs`` signed by ``key`` whose certificate is ``signer_cert``
    (None: a self-signed certificate signing itself)."""
    r, s = decode_dss_signature(key.sign(signing_input(tbs, signer_cert), _ECDSA))
    return r.to_bytes(32, "big"), s.to_bytes(32, "big")


def verify(
    key: ec.EllipticCurvePublicKey, r: bytes, s: bytes, tbs: bytes, signer_cert: bytes | None
) -> bool:
    """Whether (r, s) is ``key``'s signature of ``tbs`` (see ``sign``)."""
    # r is sent as the x coordinate of the signature's point R (x-only or compressed);
    # ECDSA's r is that x reduced mod the group order.
    der = encode_dss_signature(int.from_bytes(r, "big") % _ORDER, int.from_bytes(s, "big"))
    try:
        key.verify(der, signing_input(tbs, signer_cert), _ECDSA)
    except InvalidSignature:
        return False
    return True


def signature_value(r: bytes, s: bytes) -> tuple[str, dict[str, Any]]:
    """The ASN.1 ``Signature`` value of (r, s)."""
    return ("ecdsaNistP256Signature", {"rSig": ("x-only", r), "sSig": s})


def signature_parts(value: tuple[str, Any]) -> tuple[bytes, bytes]:
    """(r, s) of an ASN.1 ``Signature`` value; ``CertificateError`` if not NIST P-256 ECDSA
    with an x-only or compressed r."""
    kind, sig = value
    if kind != "ecdsaNistP256Signature":
        raise CertificateError(f"signature is {kind}, only ecdsaNistP256Signature is accepted")
    r_kind, r = sig["rSig"]
    if r_kind not in ("x-only", "compressed-y-0", "compressed-y-1"):
        raise CertificateError(f"signature r is {r_kind}")
    return bytes(r), bytes(sig["sSig"])


def public_point(key: ec.EllipticCurvePublicKey) -> tuple[str, bytes]:
    """A P-256 public key as the ASN.1 ``EccP256CurvePoint`` (compressed)."""
    nums = key.public_numbers()
    return ("compressed-y-1" if nums.y & 1 else "compressed-y-0", nums.x.to_bytes(32, "big"))


def key_of_point(point: tuple[str, Any]) -> ec.EllipticCurvePublicKey:
    """The public key of an ASN.1 ``EccP256CurvePoint``; ``CertificateError`` if not one."""
    kind, v = point
    try:
        if kind == "compressed-y-0":
            return ec.EllipticCurvePublicKey.from_encoded_point(_CURVE, b"\x02" + bytes(v))
        if kind == "compressed-y-1":
            return ec.EllipticCurvePublicKey.from_encoded_point(_CURVE, b"\x03" + bytes(v))
        if kind == "uncompressedP256":
            return ec.EllipticCurvePublicKey.from_encoded_point(
                _CURVE, b"\x04" + bytes(v["x"]) + bytes(v["y"])
            )
    except ValueError:
        raise CertificateError("public key is not a point on P-256") from None
    raise CertificateError(f"public key given as {kind}")


@dataclass(frozen=True)
class Certificate:
    """A parsed explicit certificate.

    Attributes:
        coer: its canonical OER encoding (what is hashed and sent).
        digest: HashedId8.
        name: ``id.name`` (e.g. ``lab.vehicle-1``).
        issuer: the issuer's HashedId8, None when self-signed.
        psids: ``appPermissions`` PSIDs.
        can_issue: has ``certIssuePermissions`` (an authority).
        valid_from, valid_until: validity, Unix seconds.
        public_key: the holder's verification key.
        tbs: COER of ``toBeSigned``; r, s: the issuer's signature.
    """

    coer: bytes
    digest: bytes
    name: str
    issuer: bytes | None
    psids: frozenset[int]
    can_issue: bool
    valid_from: float
    valid_until: float
    public_key: ec.EllipticCurvePublicKey
    tbs: bytes
    r: bytes
    s: bytes

    @property
    def hashed_id3(self) -> bytes:
        return self.digest[-3:]

    def valid_at(self, unix_s: float) -> bool:
        return self.valid_from <= unix_s <= self.valid_until


_DURATION_S = {
    "microseconds": 1e-6,
    "milliseconds": 1e-3,
    "seconds": 1.0,
    "minutes": 60.0,
    "hours": 3600.0,
    "sixtyHours": 216000.0,
    "years": 31556952.0,
}


def make_certificate(
    name: str,
    public_key: ec.EllipticCurvePublicKey,
    *,
    psids: tuple[int, ...],
    start_unix: float,
    duration_hours: int,
    issuer: tuple[Certificate, ec.EllipticCurvePrivateKey] | None,
    self_key: ec.EllipticCurvePrivateKey | None = None,
    can_issue: bool = False,
) -> Certificate:
    """Build and sign an explicit certificate.

    ``issuer``: (authority certificate, its private key); None for a self-signed root,
    which then needs ``self_key`` (the private key of ``public_key``).
    """
    if not 0 < duration_hours <= 65535:
        raise ConfigError(f"certificate duration must be 1..65535 hours, got {duration_hours}")
    tbs_value: dict[str, Any] = {
        "id": ("name", name),
        "cracaId": b"\x00\x00\x00",
        "crlSeries": 0,
        "validityPeriod": {"start": time32(start_unix), "duration": ("hours", duration_hours)},
        "appPermissions": [{"psid": p} for p in psids],
        "verifyKeyIndicator": ("verificationKey", ("ecdsaNistP256", public_point(public_key))),
    }
    if can_issue:
        tbs_value["certIssuePermissions"] = [
            {"subjectPermissions": ("all", None), "minChainLength": 1, "chainLengthRange": 0}
        ]
    tbs = spec().encode("ToBeSignedCertificate", tbs_value)
    if issuer is None:
        if self_key is None:
            raise ValueError("a self-signed certificate needs its private key")
        r, s = sign(self_key, tbs, None)
        issuer_id: tuple[str, Any] = ("self", "sha256")
    else:
        issuer_cert, issuer_key = issuer
        r, s = sign(issuer_key, tbs, issuer_cert.coer)
        issuer_id = ("sha256AndDigest", issuer_cert.digest)
    value = {
        "version": 3,
        "type": "explicit",
        "issuer": issuer_id,
        "toBeSigned": tbs_value,
        "signature": signature_value(r, s),
    }
    return parse_certificate(spec().encode("CertificateBase", value))


def parse_certificate(coer: bytes) -> Certificate:
    """Parse an explicit certificate's COER; ``CertificateError`` if it is not one we can
    use (implicit, unsigned, not P-256, no name)."""
    coer = bytes(coer)
    try:
        v = spec().decode("CertificateBase", coer)
        canonical = spec().encode("CertificateBase", v) == coer
    except Exception as exc:  # asn1tools raises many types on garbage
        raise CertificateError(f"not an IEEE 1609.2 certificate: {exc}") from None
    if not canonical:
        # Octets the decoder skipped (e.g. appended) would give one certificate many
        # digests: one cache entry each, and a signature that still verifies (D51).
        raise CertificateError("certificate is not canonical OER (re-encoding differs)")
    return certificate_of_value(v, coer)


def certificate_of_value(v: dict[str, Any], coer: bytes) -> Certificate:
    """A ``Certificate`` from a decoded ``CertificateBase`` and its COER bytes
    (``CertificateError`` for any value asn1tools cannot re-encode)."""
    try:
        return _certificate_of_value(v, coer)
    except CertificateError:
        raise
    except Exception as exc:  # e.g. asn1tools' EncodeError on an unknown CHOICE (D55)
        raise CertificateError(f"unusable certificate: {type(exc).__name__}: {exc}") from None


def _certificate_of_value(v: dict[str, Any], coer: bytes) -> Certificate:
    if v["type"] != "explicit" or "signature" not in v:
        raise CertificateError("only explicit, signed certificates are accepted")
    tbs_v = v["toBeSigned"]
    id_kind, name = tbs_v["id"]
    if id_kind != "name":
        raise CertificateError(f"certificate id is {id_kind}, expected a name")
    vk_kind, vk = tbs_v["verifyKeyIndicator"]
    if vk_kind != "verificationKey" or vk[0] != "ecdsaNistP256":
        raise CertificateError("certificate key is not an ECDSA NIST P-256 verification key")
    issuer_kind, issuer_v = v["issuer"]
    if issuer_kind == "self":
        issuer = None
    elif issuer_kind == "sha256AndDigest":
        issuer = bytes(issuer_v)
    else:
        raise CertificateError(f"certificate issuer is {issuer_kind}")
    r, s = signature_parts(v["signature"])
    start = unix_of_time32(tbs_v["validityPeriod"]["start"])
    d_kind, d = tbs_v["validityPeriod"]["duration"]
    return Certificate(
        coer=coer,
        digest=hashed_id8(coer),
        name=str(name),
        issuer=issuer,
        psids=frozenset(p["psid"] for p in tbs_v.get("appPermissions", ())),
        can_issue="certIssuePermissions" in tbs_v,
        valid_from=start,
        valid_until=start + d * _DURATION_S[d_kind],
        public_key=key_of_point(vk[1]),
        tbs=spec().encode("ToBeSignedCertificate", tbs_v),
        r=r,
        s=s,
    )


def check_issued_by(cert: Certificate, authority: Certificate, now_unix: float) -> None:
    """``CertificateError`` unless ``cert`` is ``authority`` itself or was issued and
    signed by it, and is valid at ``now_unix`` (and within the authority's validity)."""
    if cert.digest == authority.digest:
        issuer_cert = None
    elif cert.issuer == authority.digest:
        issuer_cert = authority.coer
    else:
        raise CertificateError(
            f"certificate {cert.name!r} was not issued by this convoy's authority"
        )
    if not authority.can_issue:
        raise CertificateError(
            f"authority certificate {authority.name!r} may not issue certificates"
        )
    if not verify(authority.public_key, cert.r, cert.s, cert.tbs, issuer_cert):
        raise CertificateError(
            f"certificate {cert.name!r}: the authority's signature does not verify"
        )
    if not (cert.valid_at(now_unix) and authority.valid_at(now_unix)):
        raise CertificateError(f"certificate {cert.name!r} is not valid now")
