"""The convoy's key files: ``openconvoy keys init | issue`` and loading them to sign/verify.

A convoy file ``lab.toml`` keeps its keys in ``lab.keys/`` beside it (or ``[v2v] keys``)::

    authority.key, authority.cert      the convoy authority (self-signed root)
    vehicle-N.key, vehicle-N.cert      vehicle N's key and certificate, issued by it
    revoked                            superseded certificates (HashedId8 hex, one a line)

Private keys are PKCS#8 PEM, written 0600; certificates are their IEEE 1609.2 COER
encoding. A vehicle needs only ``authority.cert``, ``revoked`` and its own pair; the
authority key can stay on the operator's machine. Problems are one-line
``KeyFileError``s naming the file.

As ssh does with its keys, a private key readable by others, or a keys directory others
may write to, is refused; so is any key file that is not a regular file or is larger
than ``MAX_KEY_FILE_BYTES``. Re-issuing a vehicle's key (``keys issue --force``) adds the
old certificate to ``revoked``, which every vehicle reads at start: copy the keys
directory's ``revoked`` to every vehicle with the new pair.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from openconvoy.comms.security import certs as c
from openconvoy.comms.security.auth import Credentials, authority_name, vehicle_name, vehicle_of
from openconvoy.core.errors import InputFileError

AUTHORITY = "authority"
AUTHORITY_HOURS = 5 * 8766  # five years
VEHICLE_HOURS = 8766  # one year
#: Certificates start this long before they are made, for clocks a little behind.
START_SLACK_S = 3600.0
#: No key, certificate or revocation file of ours is near this size (octets).
MAX_KEY_FILE_BYTES = 64 * 1024
REVOKED = "revoked"


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
    """The bytes of a key file: a regular file of at most ``MAX_KEY_FILE_BYTES`` (a FIFO
    or a device is refused, never waited on or read without end)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise KeyFileError(f"{what} not found: {path}") from None
    except OSError as exc:
        raise KeyFileError(f"cannot read {what} {path}: {exc.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"{what} {path} is not a regular file")
        if st.st_size > MAX_KEY_FILE_BYTES:
            raise KeyFileError(
                f"{what} {path} is {st.st_size} octets, larger than any key file "
                f"({MAX_KEY_FILE_BYTES})"
            )
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_KEY_FILE_BYTES + 1)
    except OSError as exc:
        raise KeyFileError(f"cannot read {what} {path}: {exc.strerror}") from None
    finally:
        os.close(fd)
    if len(data) > MAX_KEY_FILE_BYTES:
        raise KeyFileError(f"{what} {path} is larger than any key file ({MAX_KEY_FILE_BYTES})")
    return data


def check_protected(key_path: Path) -> None:
    """``KeyFileError`` when a private key is readable or writable by others, or its
    directory writable by others (ssh's rule: fix with ``chmod 600 KEY``,
    ``chmod 700 DIR``)."""
    for p, bits, fix in (
        (key_path, 0o077, f"chmod 600 {key_path}"),
        (key_path.parent, 0o022, f"chmod 700 {key_path.parent}"),
    ):
        try:
            st = os.stat(p)
        except OSError:
            continue  # reading it says what is wrong
        if p is key_path and not stat.S_ISREG(st.st_mode):
            raise KeyFileError(f"private key {p} is not a regular file")
        mode = stat.S_IMODE(st.st_mode)
        if mode & bits:
            raise KeyFileError(
                f"{p} is accessible by others (mode {mode:04o}): refused, as ssh does (run `{fix}`)"
            )


def read_key(path: str | Path) -> ec.EllipticCurvePrivateKey:
    """A P-256 private key from a PEM file."""
    p = Path(path)
    check_protected(p)
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
    keys_dir: str | Path, convoy: str, vehicle_index: int, now: float, *, force: bool = False
) -> c.Certificate:
    """Issue vehicle ``vehicle_index``'s key and certificate, signed by the authority.

    A vehicle that has a certificate already gets a new one only with ``force``; the old
    one is then revoked (added to ``revoked``), so a stolen or lost key stops working on
    every vehicle given the new ``revoked`` file. Vehicle certificates may sign BSMs;
    the leader's (vehicle 0) also its scenario's completion; aborts only the authority
    (or an operator's key)."""
    if vehicle_index < 0:
        raise KeyFileError(f"--vehicle-id must be >= 0, got {vehicle_index}")
    authority, akey = load_authority(keys_dir, with_key=True)
    assert akey is not None
    d = Path(keys_dir)
    stem = vehicle_stem(vehicle_index)
    old_path = d / f"{stem}.cert"
    if old_path.exists() or (d / f"{stem}.key").exists():
        if not force:
            raise KeyFileError(
                f"vehicle {vehicle_index} already has a key in {d} (use --force to issue a "
                "new one and revoke the old certificate)"
            )
        if old_path.exists():
            try:
                revoke(d, read_certificate(old_path))
            except KeyFileError:
                pass  # an unreadable old certificate was never usable
    key = ec.generate_private_key(ec.SECP256R1())
    # Vehicles sign BSMs and plans; the leader also its scenario's completion; aborts only
    # the authority or an operator key.
    psids = (c.PSID_BSM, c.PSID_PLAN) + ((c.PSID_COMPLETE,) if vehicle_index == 0 else ())
    cert = c.make_certificate(
        vehicle_name(convoy, vehicle_index),
        key.public_key(),
        psids=psids,
        start_unix=now - START_SLACK_S,
        duration_hours=VEHICLE_HOURS,
        issuer=(authority, akey),
    )
    _write_pair(d, stem, key, cert)
    return cert


def issue_operator(
    keys_dir: str | Path, convoy: str, name: str, now: float, *, force: bool = False
) -> c.Certificate:
    """Issue an operator's key and certificate (``operator-NAME``): it may sign aborts
    (``openconvoy abort --key``) and nothing else; re-issuing needs ``force`` and revokes
    the old one."""
    if not name or not all(ch.isalnum() or ch in "-_" for ch in name) or len(name) > 32:
        raise KeyFileError(f"--name {name!r}: letters, digits, - and _ only (at most 32)")
    authority, akey = load_authority(keys_dir, with_key=True)
    assert akey is not None
    d = Path(keys_dir)
    stem = f"operator-{name}"
    old_path = d / f"{stem}.cert"
    if old_path.exists() or (d / f"{stem}.key").exists():
        if not force:
            raise KeyFileError(
                f"operator {name} already has a key in {d} (use --force to issue a new one "
                "and revoke the old certificate)"
            )
        if old_path.exists():
            try:
                revoke(d, read_certificate(old_path))
            except KeyFileError:
                pass
    key = ec.generate_private_key(ec.SECP256R1())
    cert = c.make_certificate(
        f"{convoy}.{stem}",
        key.public_key(),
        psids=(c.PSID_ABORT,),
        start_unix=now - START_SLACK_S,
        duration_hours=VEHICLE_HOURS,
        issuer=(authority, akey),
    )
    _write_pair(d, stem, key, cert)
    return cert


def revoke(keys_dir: str | Path, cert: c.Certificate) -> None:
    """Add ``cert`` to the keys directory's ``revoked`` list (kept, never rewritten)."""
    p = Path(keys_dir) / REVOKED
    if cert.digest in load_revoked(keys_dir):
        return
    with open(p, "a", encoding="ascii") as f:
        f.write(f"{cert.digest.hex()} {cert.name}\n")


def load_revoked(keys_dir: str | Path) -> frozenset[bytes]:
    """The HashedId8s listed in ``revoked`` (none when there is no such file); each line
    is ``HEX16 [name]``; anything else is a one-line ``KeyFileError``."""
    p = Path(keys_dir) / REVOKED
    if not p.exists():
        return frozenset()
    out = set()
    for n, line in enumerate(_read(p, "revocation list").decode("ascii", "replace").splitlines()):
        word = line.split(maxsplit=1)[0] if line.strip() else ""
        if not word or word.startswith("#"):
            continue
        try:
            digest = bytes.fromhex(word)
        except ValueError:
            digest = b""
        if len(digest) != 8:
            raise KeyFileError(f"{p}:{n + 1}: not a certificate digest (16 hex digits): {word!r}")
        out.add(digest)
    return frozenset(out)


def load_signer(
    key_path: str | Path,
    authority: c.Certificate,
    now: float,
    revoked: frozenset[bytes] = frozenset(),
) -> Credentials:
    """Credentials from a private key file and the certificate beside it (same name,
    ``.cert``), checked to match, to be issued by ``authority`` and not ``revoked``."""
    kp = Path(key_path)
    cp = kp.with_suffix(".cert")
    key = read_key(kp)
    cert = read_certificate(cp)
    _matching(key, cert, kp, cp)
    try:
        c.check_issued_by(cert, authority, now)
    except c.CertificateError as exc:
        raise KeyFileError(f"{cp}: {exc}") from None
    if cert.digest in revoked:
        raise KeyFileError(f"{cp}: certificate {cert.name!r} is revoked (re-issued since)")
    return Credentials(authority, cert, key, revoked)


def load_vehicle(keys_dir: str | Path, vehicle_index: int, now: float) -> Credentials:
    """Vehicle ``vehicle_index``'s credentials from the convoy's keys directory (its
    certificate must name that vehicle), with the directory's revocation list."""
    authority, _ = load_authority(keys_dir)
    kp = Path(keys_dir) / f"{vehicle_stem(vehicle_index)}.key"
    if not kp.exists():
        raise KeyFileError(
            f"no key for vehicle {vehicle_index} in {keys_dir} "
            f"(run `openconvoy keys issue --vehicle-id {vehicle_index}`)"
        )
    creds = load_signer(kp, authority, now, load_revoked(keys_dir))
    assert creds.certificate is not None
    if vehicle_of(creds.certificate) != vehicle_index:
        raise KeyFileError(
            f"{kp.with_suffix('.cert')}: the certificate is {creds.certificate.name!r}, "
            f"not vehicle {vehicle_index}'s"
        )
    return creds


def signer_of_key(key_path: str | Path, keys_dir: str | Path | None, now: float) -> Credentials:
    """Credentials of any convoy key file (a vehicle's or the authority's), trusting the
    authority of ``keys_dir`` (default: the directory the key is in)."""
    d = keys_dir if keys_dir is not None else Path(key_path).parent
    authority, _ = load_authority(d)
    return load_signer(key_path, authority, now, load_revoked(d))
