"""The convoy's key files: ``openconvoy keys init | issue`` and loading them to sign/verify.

A convoy file ``lab.toml`` keeps its keys in ``lab.keys/`` beside it (or ``[v2v] keys``)::

    authority.key, authority.cert      the convoy authority (self-signed root)
    vehicle-N.key, vehicle-N.cert      vehicle N's key and certificate, issued by it

Private keys are PKCS#8 PEM, written 0600; certificates are their IEEE 1609.2 COER
encoding. A vehicle needs only ``authority.cert`` and its own pair; the authority key can
stay on the operator's machine. Problems are one-line ``KeyFileError``s naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from openconvoy.comms.security import certs as c
from openconvoy.comms.security.auth import Credentials, authority_name, vehicle_name
from openconvoy.core.errors import InputFileError

AUTHORITY = "authority"
AUTHORITY_HOURS = 5 * 8766  # five years
VEHICLE_HOURS = 8766  # one year
#: Certificates start this long before they are made, for clocks a little behind.
START_SLACK_S = 3600.0


class KeyFileError(InputFileError):
    """A key or certificate file is missing, unreadable, or does not match (one line)."""


def default_keys_dir(convoy_path: str | Path) -> Path:
    """``lab.keys/`` beside ``lab.toml``."""
    p = Path(convoy_path)
    return p.with_name(p.stem + ".keys")


def vehicle_stem(vehicle_index: int) -> str:
    return f"vehicle-{vehicle_index}"


def has_keys(keys_dir: str | Path) -> bool:
    """Whether the convoy has keys (its authority certificate exists)."""
    return (Path(keys_dir) / f"{AUTHORITY}.cert").is_file()


def _write_private(path: Path, data: bytes) -> None:
    # Created 0600 from the start: never briefly readable by others.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, data)
    finally:
        os.close(fd)


def _write_pair(
    keys_dir: Path, stem: str, key: ec.EllipticCurvePrivateKey, cert: c.Certificate
) -> None:
    keys_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    _write_private(keys_dir / f"{stem}.key", pem)
    _write_private(keys_dir / f"{stem}.cert", cert.coer)


def _read(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise KeyFileError(f"{what} not found: {path}") from None
    except OSError as exc:
        raise KeyFileError(f"cannot read {what} {path}: {exc.strerror}") from None


def read_key(path: str | Path) -> ec.EllipticCurvePrivateKey:
    """A P-256 private key from a PEM file."""
    p = Path(path)
    data = _read(p, "private key")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise KeyFileError(f"{p}: not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or not isinstance(key.curve, ec.SECP256R1):
        raise KeyFileError(f"{p}: not a NIST P-256 (secp256r1) key")
    return key


def read_certificate(path: str | Path) -> c.Certificate:
    """A certificate from its COER file."""
    p = Path(path)
    try:
        return c.parse_certificate(_read(p, "certificate"))
    except c.CertificateError as exc:
        raise KeyFileError(f"{p}: {exc}") from None


def _matching(
    key: ec.EllipticCurvePrivateKey, cert: c.Certificate, key_path: Path, cert_path: Path
) -> None:
    if key.public_key().public_numbers() != cert.public_key.public_numbers():
        raise KeyFileError(f"{key_path} does not match the certificate {cert_path}")


def init_authority(
    keys_dir: str | Path, convoy: str, now: float, *, force: bool = False
) -> c.Certificate:
    """Make the convoy authority's key and self-signed certificate in ``keys_dir``."""
    d = Path(keys_dir)
    if has_keys(d) and not force:
        raise KeyFileError(f"{d} already holds a convoy authority (use --force to replace it)")
    key = ec.generate_private_key(ec.SECP256R1())
    cert = c.make_certificate(
        authority_name(convoy),
        key.public_key(),
        psids=(c.PSID_ABORT,),
        start_unix=now - START_SLACK_S,
        duration_hours=AUTHORITY_HOURS,
        issuer=None,
        self_key=key,
        can_issue=True,
    )
    _write_pair(d, AUTHORITY, key, cert)
    return cert


def load_authority(
    keys_dir: str | Path, *, with_key: bool = False
) -> tuple[c.Certificate, ec.EllipticCurvePrivateKey | None]:
    """The authority certificate (and key, ``with_key``), checked to match."""
    d = Path(keys_dir)
    cert_path, key_path = d / f"{AUTHORITY}.cert", d / f"{AUTHORITY}.key"
    if not cert_path.exists():
        raise KeyFileError(f"no convoy authority in {d} (run `openconvoy keys init` first)")
    cert = read_certificate(cert_path)
    if cert.issuer is not None or not cert.can_issue:
        raise KeyFileError(f"{cert_path} is not a convoy authority certificate")
    key = None
    if with_key:
        key = read_key(key_path)
        _matching(key, cert, key_path, cert_path)
    return cert, key


def issue_vehicle(
    keys_dir: str | Path, convoy: str, vehicle_index: int, now: float
) -> c.Certificate:
    """Issue vehicle ``vehicle_index``'s key and certificate, signed by the authority."""
    if vehicle_index < 0:
        raise KeyFileError(f"--vehicle-id must be >= 0, got {vehicle_index}")
    authority, akey = load_authority(keys_dir, with_key=True)
    assert akey is not None
    key = ec.generate_private_key(ec.SECP256R1())
    cert = c.make_certificate(
        vehicle_name(convoy, vehicle_index),
        key.public_key(),
        psids=(c.PSID_BSM, c.PSID_ABORT, c.PSID_PLAN),
        start_unix=now - START_SLACK_S,
        duration_hours=VEHICLE_HOURS,
        issuer=(authority, akey),
    )
    _write_pair(Path(keys_dir), vehicle_stem(vehicle_index), key, cert)
    return cert


def load_signer(key_path: str | Path, authority: c.Certificate, now: float) -> Credentials:
    """Credentials from a private key file and the certificate beside it (same name,
    ``.cert``), checked to match and to be issued by ``authority``."""
    kp = Path(key_path)
    cp = kp.with_suffix(".cert")
    key = read_key(kp)
    cert = read_certificate(cp)
    _matching(key, cert, kp, cp)
    try:
        c.check_issued_by(cert, authority, now)
    except c.CertificateError as exc:
        raise KeyFileError(f"{cp}: {exc}") from None
    return Credentials(authority, cert, key)


def load_vehicle(keys_dir: str | Path, vehicle_index: int, now: float) -> Credentials:
    """Vehicle ``vehicle_index``'s credentials from the convoy's keys directory."""
    authority, _ = load_authority(keys_dir)
    kp = Path(keys_dir) / f"{vehicle_stem(vehicle_index)}.key"
    if not kp.exists():
        raise KeyFileError(
            f"no key for vehicle {vehicle_index} in {keys_dir} "
            f"(run `openconvoy keys issue --vehicle-id {vehicle_index}`)"
        )
    return load_signer(kp, authority, now)


def signer_of_key(key_path: str | Path, keys_dir: str | Path | None, now: float) -> Credentials:
    """Credentials of any convoy key file (a vehicle's or the authority's), trusting the
    authority of ``keys_dir`` (default: the directory the key is in)."""
    authority, _ = load_authority(keys_dir if keys_dir is not None else Path(key_path).parent)
    return load_signer(key_path, authority, now)
