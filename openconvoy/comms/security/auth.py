"""Authenticated V2V: signing what a vehicle sends, verifying what it hears, replay checks.

``Authenticator`` is one vehicle's (or one listener's) side of IEEE 1609.2 signed SPDUs
(``security.spdu``) under the convoy's authority (``security.certs``):

- sending: ``sign(payload, psid, now)``; the signer is the certificate's digest, or the
  full certificate once a second, on the first message, and right after another station
  asked for it (its ``inlineP2pcdRequest`` named our HashedId3, the peer-to-peer
  certificate distribution of IEEE 1609.2);
- receiving: ``check(spdu, now)`` finds the signer's certificate (cached per digest once
  verified against the authority, so a BSM costs one ECDSA verification), checks the
  PSID is permitted, the signature, and freshness; ``admit`` then records the message
  for the replay checks. A digest not yet known is dropped (``unknown_signer``) and
  asked for in our next SPDU.

Replay and freshness (``ReplayGuard``): a message is rejected when its generation time is
more than ``window_s`` (default ``mapping.DEFAULT_TIME_TOLERANCE_S``, 1 s: the link's one
clock tolerance) in the past (``stale``) or the future (``future``);
when its (certificate, generation time) was already accepted (``duplicate``); or when the
sender's generation time and msgCnt both go backwards (``backwards``: an older message
replayed within the window; a clock stepped back with msgCnt going on is not).

Bounded state (D51): only canonical certificates are learned (re-encoding gives the same
octets), at most ``MAX_CERTS`` of them (least recently used forgotten first; the authority
and our own stay), at most ``_MAX_BAD_CERTS`` remembered as bad. Certificates listed in
``Credentials.revoked`` (the keys directory's ``revoked`` file) are refused.

Every rejection has one reason from ``REASONS``; ``rejected`` counts them. Pure: times are
arguments (Unix seconds); no I/O.
"""

from __future__ import annotations

import re
from collections import OrderedDict, deque
from dataclasses import dataclass, field

from cryptography.hazmat.primitives.asymmetric import ec

from openconvoy.comms.mapping import DEFAULT_TIME_TOLERANCE_S
from openconvoy.comms.security import certs as c
from openconvoy.comms.security.spdu import SignedSpdu, encode_signed
from openconvoy.core.errors import ConfigError

DEFAULT_WINDOW_S = DEFAULT_TIME_TOLERANCE_S
CERT_PERIOD_S = 1.0
#: Verified certificates kept (besides the authority's and our own): a convoy needs one
#: per member and operator; more only costs a re-verification when one comes back.
MAX_CERTS = 64
#: A message rejected as stale or future is verified anyway, at most this often per
#: signer (s), to measure how far off that signer's clock is (``probe_skew``).
SKEW_PROBE_PERIOD_S = 1.0
#: ... and at most this many such verifications per period in all.
SKEW_PROBES_PER_PERIOD = 8

REASONS = (
    "unsigned",  # auth required, the datagram is not a signed SPDU
    "malformed",  # a signed SPDU we cannot read, or its payload is not a valid message
    "unknown_signer",  # signed by a certificate digest we do not know (yet)
    "bad_certificate",  # not issued by the convoy's authority, not valid, not canonical
    "revoked",  # a certificate in the convoy's revocation list
    "not_permitted",  # the certificate may not sign this PSID
    "bad_signature",  # the signature does not verify
    "wrong_sender",  # a member's certificate signing another member's BSM
    "stale",  # generated more than the window ago
    "future",  # generated more than the window ahead of our clock
    "duplicate",  # (certificate, generation time) already accepted
    "backwards",  # the sender's generation time and msgCnt went backwards
)

_VEHICLE_NAME = re.compile(r"\.vehicle-(\d+)$")
_MAX_BAD_CERTS = 1024
_MAX_REQUESTS = 8


def authority_name(convoy: str) -> str:
    """The ``id.name`` of a convoy's authority certificate."""
    return f"{convoy}.authority"


def vehicle_name(convoy: str, vehicle_index: int) -> str:
    """The ``id.name`` of vehicle ``vehicle_index``'s certificate."""
    return f"{convoy}.vehicle-{vehicle_index}"


def vehicle_of(cert: c.Certificate) -> int | None:
    """The convoy index a certificate is issued to (None: the authority or an operator)."""
    m = _VEHICLE_NAME.search(cert.name)
    return int(m.group(1)) if m else None


@dataclass(frozen=True)
class Credentials:
    """What a station holds: the convoy's authority certificate (the trust anchor) and,
    to sign, its own private key and certificate."""

    authority: c.Certificate
    certificate: c.Certificate | None = None
    key: ec.EllipticCurvePrivateKey | None = None
    revoked: frozenset[bytes] = frozenset()
    """HashedId8s of certificates no longer accepted (``keystore.load_revoked``)."""

    @property
    def can_sign(self) -> bool:
        return self.certificate is not None and self.key is not None


def _behind(cnt: int, last: int) -> bool:
    """msgCnt ``cnt`` is before ``last`` (mod 128, within half the range)."""
    return 0 < (last - cnt) % 128 < 64


def _replay_key(spdu: SignedSpdu) -> bytes:
    """The stream an SPDU's replay checks run in: the signer's digest; plan messages
    (``PSID_PLAN``) in a stream of their own, since a plan goes out with each BSM, at the
    same instant, and is no replay of it."""
    if spdu.psid == c.PSID_PLAN:
        return spdu.digest + c.PSID_PLAN.to_bytes(4, "big")
    return spdu.digest


class ReplayGuard:
    """Freshness, duplicate and order checks per signer certificate (times in Unix s)."""

    def __init__(self, window_s: float = DEFAULT_WINDOW_S) -> None:
        if not window_s > 0:
            raise ConfigError(f"replay window must be > 0 s, got {window_s}")
        self.window_s = window_s
        self._seen: set[tuple[bytes, int]] = set()
        self._expiry: deque[tuple[float, tuple[bytes, int]]] = deque()
        self._last: dict[bytes, tuple[int, int | None]] = {}

    def precheck(self, digest: bytes, generation_time: int, now: float) -> str | None:
        """``stale``, ``future`` or ``duplicate``, else None. Records nothing."""
        age = now - c.unix_of_time64(generation_time)
        if age > self.window_s:
            return "stale"
        if -age > self.window_s:
            return "future"
        if (digest, generation_time) in self._seen:
            return "duplicate"
        return None

    def order(self, digest: bytes, generation_time: int, msg_cnt: int | None) -> str | None:
        """``backwards`` if this sender's time and msgCnt both went back, else None."""
        last = self._last.get(digest)
        if last is None or generation_time >= last[0]:
            return None
        if msg_cnt is None or last[1] is None or _behind(msg_cnt, last[1]):
            return "backwards"
        return None

    def record(self, digest: bytes, generation_time: int, msg_cnt: int | None, now: float) -> None:
        """Remember an accepted message (forgotten once it would be stale anyway)."""
        key = (digest, generation_time)
        self._seen.add(key)
        self._expiry.append((c.unix_of_time64(generation_time) + self.window_s, key))
        while self._expiry and self._expiry[0][0] < now:
            self._seen.discard(self._expiry.popleft()[1])
        last = self._last.get(digest)
        if last is None or generation_time >= last[0]:
            self._last[digest] = (generation_time, msg_cnt)


@dataclass
class AuthCounters:
    """Rejections by reason (``REASONS``) and certificate traffic."""

    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REASONS, 0))
    certificates_learned: int = 0
    certificates_sent: int = 0
    requests_sent: int = 0

    @property
    def total_rejected(self) -> int:
        return sum(self.rejected.values())


class Authenticator:
    """Signs and verifies SPDUs for one station (see the module docstring).

    Args:
        credentials: the authority certificate, and our key and certificate to sign.
        window_s: the replay window (s).
        psids: the PSIDs accepted on receive.
    """

    def __init__(
        self,
        credentials: Credentials,
        *,
        window_s: float = DEFAULT_WINDOW_S,
        psids: frozenset[int] = frozenset({c.PSID_BSM, c.PSID_ABORT, c.PSID_COMPLETE, c.PSID_PLAN}),
    ) -> None:
        self.credentials = credentials
        self.psids = psids
        self.guard = ReplayGuard(window_s)
        self.counters = AuthCounters()
        authority = credentials.authority
        self._pinned: dict[bytes, c.Certificate] = {authority.digest: authority}
        self._certs: OrderedDict[bytes, c.Certificate] = OrderedDict()  # learned, LRU
        self._bad: dict[bytes, str] = {}
        own = credentials.certificate
        self.own_digest = own.digest if own is not None else None
        if own is not None:
            self._pinned[own.digest] = own
        self._probed: dict[bytes, float] = {}  # digest -> last skew probe (Unix s)
        self._probe_window = (-float("inf"), 0)  # (start, probes in it)
        self._t_cert = -float("inf")
        self._cert_asked = False
        self._requests: dict[bytes, None] = {}  # HashedId3 of unknown digests, in order

    # ---------------------------------------------------------------- sending

    def sign(self, payload: bytes, psid: int, now: float) -> bytes:
        """A signed SPDU of ``payload`` generated at ``now`` (Unix s)."""
        cred = self.credentials
        if cred.key is None or cred.certificate is None:
            raise ValueError("signing needs a private key and its certificate")
        full = self._cert_asked or now - self._t_cert >= CERT_PERIOD_S
        if full:
            self._t_cert, self._cert_asked = now, False
            self.counters.certificates_sent += 1
        requests = tuple(self._requests)
        if requests:
            self._requests.clear()
            self.counters.requests_sent += 1
        return encode_signed(
            payload,
            psid=psid,
            generation_time=c.time64(now),
            key=cred.key,
            certificate=cred.certificate,
            include_certificate=full,
            p2pcd_request=requests,
        )

    # ---------------------------------------------------------------- receiving

    def reject(self, reason: str) -> None:
        """Count a rejection (also for reasons found outside, e.g. ``unsigned``)."""
        self.counters.rejected[reason] += 1

    def check(self, spdu: SignedSpdu, now: float) -> c.Certificate | str:
        """The signer's verified certificate, or why ``security.spdu`` is rejected (counted).

        Checks, cheapest first: PSID, freshness and duplicates, the signer's certificate
        (known digest, or a sent certificate issued by the authority), its permission
        for the PSID, the signature. Records nothing for the replay checks (``admit``)."""
        reason = self._check(spdu, now)
        if isinstance(reason, str):
            self.counters.rejected[reason] += 1
        return reason

    def precheck(self, spdu: SignedSpdu, now: float) -> str | None:
        """The cheap part of ``check`` (PSID, freshness, duplicates, revoked or known-bad
        signer; no signature verified): why it is rejected (counted), else None."""
        reason = self._precheck(spdu, now)
        if reason is not None:
            self.counters.rejected[reason] += 1
        return reason

    def _precheck(self, spdu: SignedSpdu, now: float) -> str | None:
        if spdu.psid not in self.psids:
            return "not_permitted"
        reason = self.guard.precheck(_replay_key(spdu), spdu.generation_time, now)
        if reason is not None:
            return reason
        if spdu.digest in self.credentials.revoked:
            return "revoked"
        if spdu.digest in self._bad:
            return "bad_certificate"
        return None

    def _check(self, spdu: SignedSpdu, now: float) -> c.Certificate | str:
        reason = self._precheck(spdu, now)
        if reason is not None:
            return reason
        cert = self.known(spdu.digest)
        if cert is None:
            if spdu.digest in self._bad:
                return "bad_certificate"
            if spdu.certificate is None:
                if len(self._requests) < _MAX_REQUESTS:
                    self._requests[spdu.digest[-3:]] = None
                return "unknown_signer"
            cert_or_reason = self._learn(spdu, now)
            if isinstance(cert_or_reason, str):
                return cert_or_reason
            cert = cert_or_reason
        elif not cert.valid_at(now):
            return "bad_certificate"
        if spdu.psid not in cert.psids:
            return "not_permitted"
        if not c.verify(cert.public_key, spdu.r, spdu.s, spdu.tbs, cert.coer):
            return "bad_signature"
        if self.own_digest is not None and self.own_digest[-3:] in spdu.p2pcd_request:
            self._cert_asked = True
        return cert

    def _learn(self, spdu: SignedSpdu, now: float) -> c.Certificate | str:
        assert spdu.certificate is not None
        try:
            self._not_a_variant(spdu.certificate)
            if spdu.certificate_value is None:
                cert = c.parse_certificate(spdu.certificate)
            else:
                cert = c.certificate_of_value(spdu.certificate_value, spdu.certificate)
            c.check_issued_by(cert, self.credentials.authority, now)
        except c.CertificateError as exc:
            if len(self._bad) >= _MAX_BAD_CERTS:
                self._bad.pop(next(iter(self._bad)))
            self._bad[spdu.digest] = str(exc)
            return "bad_certificate"
        if cert.digest in self.credentials.revoked:
            return "revoked"
        self._certs[cert.digest] = cert
        while len(self._certs) > MAX_CERTS:
            self._certs.popitem(last=False)
        self._requests.pop(cert.digest[-3:], None)
        self.counters.certificates_learned += 1
        return cert

    def _not_a_variant(self, coer: bytes) -> None:
        """``CertificateError`` when ``coer`` is a known certificate with octets added
        after it: rejected without parsing (a flood of such variants stays cheap)."""
        for known in (*self._pinned.values(), *self._certs.values()):
            n = len(known.coer)
            if len(coer) > n and coer[:n] == known.coer:
                raise c.CertificateError(f"{known.name!r} with {len(coer) - n} octets appended")

    def probe_skew(self, spdu: SignedSpdu, now: float) -> c.Certificate | None:
        """For an SPDU rejected as ``stale`` or ``future``: its signer's certificate when
        the signature verifies, to measure that signer's clock offset; at most once per
        ``SKEW_PROBE_PERIOD_S`` per digest (a flood of such SPDUs costs one verification
        a second, ``SKEW_PROBES_PER_PERIOD`` in all), None otherwise. A certificate it
        carries is learned as ``check`` would; records nothing else."""
        if spdu.digest in self.credentials.revoked or spdu.digest in self._bad:
            return None
        last = self._probed.get(spdu.digest)
        if last is not None and now - last < SKEW_PROBE_PERIOD_S:
            return None
        if now - self._probe_window[0] >= SKEW_PROBE_PERIOD_S:
            self._probe_window = (now, 0)
        if self._probe_window[1] >= SKEW_PROBES_PER_PERIOD:
            return None
        self._probe_window = (self._probe_window[0], self._probe_window[1] + 1)
        if len(self._probed) > 4 * MAX_CERTS:
            self._probed.clear()
        self._probed[spdu.digest] = now
        cert = self.known(spdu.digest)
        if cert is None and spdu.certificate is not None:
            learned = self._learn(spdu, now)
            cert = None if isinstance(learned, str) else learned
        if cert is None or spdu.psid not in cert.psids:
            return None
        ok = c.verify(cert.public_key, spdu.r, spdu.s, spdu.tbs, cert.coer)
        return cert if ok else None

    def admit(self, spdu: SignedSpdu, now: float, msg_cnt: int | None = None) -> str | None:
        """After ``check`` and decoding the payload: ``backwards`` (counted) or None, in
        which case the message is recorded as accepted."""
        reason = self.guard.order(_replay_key(spdu), spdu.generation_time, msg_cnt)
        if reason is not None:
            self.counters.rejected[reason] += 1
            return reason
        self.guard.record(_replay_key(spdu), spdu.generation_time, msg_cnt, now)
        return None

    def known(self, digest: bytes) -> c.Certificate | None:
        """The verified certificate of ``digest``, if known (and marks it recently used)."""
        cert = self._pinned.get(digest)
        if cert is not None:
            return cert
        cert = self._certs.get(digest)
        if cert is not None:
            self._certs.move_to_end(digest)
        return cert

    @property
    def certificates_cached(self) -> int:
        """Certificates held (pinned and learned): at most ``MAX_CERTS`` + 2."""
        return len(self._pinned) + len(self._certs)
