"""``openconvoy keys init | issue``, key files, and the convoy's ``[v2v] auth``."""

from __future__ import annotations

import os
import stat

import pytest

from openconvoy.cli import main
from openconvoy.comms.security import keystore as ks
from openconvoy.convoy import V2VConfig, load_convoy


@pytest.fixture
def convoy(tmp_path):
    p = tmp_path / "lab.toml"
    p.write_text('[convoy]\nname = "lab"\n')
    return p


def _err(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_init_and_issue_write_0600_files_and_turn_auth_on(convoy, capsys):
    assert load_convoy(convoy).v2v.auth_required  # fails closed: required before keys exist
    assert main(["keys", "init", "--convoy", str(convoy)]) == 0
    for i in range(3):
        assert main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", str(i)]) == 0
    d = convoy.with_name("lab.keys")
    names = sorted(p.name for p in d.iterdir())
    assert names == sorted(
        f"{s}.{e}"
        for s in ("authority", "vehicle-0", "vehicle-1", "vehicle-2")
        for e in ("key", "cert")
    )
    for p in d.iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p
    cfg = load_convoy(convoy)
    assert cfg.v2v.keys == str(d) and cfg.v2v.auth_required
    cred = ks.load_vehicle(d, 1, __import__("time").time())
    assert cred.certificate.name == "lab.vehicle-1" and cred.authority.name == "lab.authority"
    # a second init does not silently replace the authority
    assert main(["keys", "init", "--convoy", str(convoy)]) == 2
    assert "already holds a convoy authority" in _err(capsys)


def test_auth_off_and_compat_refusal(convoy, capsys):
    main(["keys", "init", "--convoy", str(convoy)])
    capsys.readouterr()
    convoy.write_text('[convoy]\nname = "lab"\n[v2v]\nauth = "off"\n')
    assert not load_convoy(convoy).v2v.auth_required
    convoy.write_text('[convoy]\nname = "lab"\n[v2v]\ncompat = true\n')
    with pytest.raises(ValueError, match="compat = true cannot be combined with authentication"):
        load_convoy(convoy)  # keys exist: auth is required by default
    with pytest.raises(ValueError, match="cannot be combined"):
        V2VConfig(compat=True, auth="required")
    with pytest.raises(ValueError, match="v2v.auth"):
        V2VConfig(auth="maybe")
    # abort on a keyed convoy without --key: one line saying what to do
    convoy.write_text('[convoy]\nname = "lab"\n')
    assert main(["abort", "--iface", "lo", "--convoy", str(convoy)]) == 2
    assert "only obeys signed aborts: give --key" in _err(capsys)


def test_missing_unreadable_and_mismatched_keys_are_one_line_errors(convoy, tmp_path, capsys):
    d = convoy.with_name("lab.keys")
    assert main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", "1"]) == 2
    line = _err(capsys)
    assert "no convoy authority in" in line and "openconvoy keys init" in line
    main(["keys", "init", "--convoy", str(convoy)])
    main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", "0"])
    main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", "1"])
    capsys.readouterr()
    now = __import__("time").time()
    with pytest.raises(ks.KeyFileError, match="no key for vehicle 2 .*keys issue --vehicle-id 2"):
        ks.load_vehicle(d, 2, now)
    # mismatched: vehicle 1's key with vehicle 0's certificate
    (d / "vehicle-1.cert").write_bytes((d / "vehicle-0.cert").read_bytes())
    with pytest.raises(ks.KeyFileError, match="vehicle-1.key does not match the certificate"):
        ks.load_vehicle(d, 1, now)
    # a certificate from another convoy's authority
    other = tmp_path / "other.keys"
    ks.init_authority(other, "other", now)
    ks.issue_vehicle(other, "other", 1, now)
    for e in ("key", "cert"):
        (d / f"vehicle-1.{e}").write_bytes((other / f"vehicle-1.{e}").read_bytes())
    with pytest.raises(ks.KeyFileError, match="not issued by this convoy's authority"):
        ks.load_vehicle(d, 1, now)
    (d / "vehicle-0.key").write_text("not a key")
    with pytest.raises(ks.KeyFileError, match="not an unencrypted PEM private key"):
        ks.load_vehicle(d, 0, now)
    (d / "authority.cert").write_bytes(b"\x00garbage")
    with pytest.raises(ks.KeyFileError, match="authority.cert: not an IEEE 1609.2 certificate"):
        ks.load_vehicle(d, 0, now)
    if os.geteuid() != 0:  # root reads anything
        (d / "vehicle-0.key").chmod(0)
        with pytest.raises(ks.KeyFileError, match="cannot read private key"):
            ks.read_key(d / "vehicle-0.key")


def test_deploy_with_keys_but_without_the_vehicles_key_fails_in_one_line(convoy, capsys):
    main(["keys", "init", "--convoy", str(convoy)])
    capsys.readouterr()
    rc = main(
        [
            "deploy",
            "--policy",
            "paper",
            "--vehicle-id",
            "1",
            "--convoy",
            str(convoy),
            "--mavlink",
            "udpout:127.0.0.1:9",
            "--iface",
            "lo",
            "--quiet",
        ]
    )
    assert rc == 2
    line = _err(capsys)
    assert "no key for vehicle 1" in line and "keys issue --vehicle-id 1" in line
