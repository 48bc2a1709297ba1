"""V2V fails closed (issue 22, D46): a deploy without keys refuses unless the convoy file says
``[v2v] auth = "off"``; then it says so at every start. In the netns demo's setting (real
IPv6 multicast in a private network namespace) and in-process."""

from __future__ import annotations

import os
import stat
import sys
import time

import pytest

from openconvoy.cli import main
from openconvoy.comms.netns import netns_unavailable_reason, run_in_netns
from openconvoy.comms.security import keystore as ks
from openconvoy.convoy import ConvoyConfig
from openconvoy.demo import deploy_argv, write_convoy_toml


def _deploy(convoy, vid=1, *extra):
    return [
        "deploy", "--policy", "paper", "--vehicle-id", str(vid), "--convoy", str(convoy),
        "--mavlink", "udpout:127.0.0.1:9", "--iface", "lo", "--connect-timeout", "1", *extra,
    ]  # fmt: skip


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.mark.netns
def test_deploy_in_the_netns_demo_without_keys_refuses_in_one_line(tmp_path):
    reason = netns_unavailable_reason()
    assert reason is None, f"this test needs a private network namespace: {reason}"
    convoy = tmp_path / "convoy.toml"
    write_convoy_toml(convoy, ConvoyConfig().vehicles, ConvoyConfig().origin, keys=False)
    off = tmp_path / "off.toml"
    write_convoy_toml(off, ConvoyConfig().vehicles, ConvoyConfig().origin, keys=False)
    off.write_text(off.read_text() + '[v2v]\nauth = "off"\n')

    def in_ns(path, vid):
        argv = deploy_argv(vid, path, "udpout:127.0.0.1:9", "IFACE", tmp_path / f"run{vid}")
        argv += ["--connect-timeout", "1"]
        cmd = " ".join(f"'{a}'" for a in argv).replace("'IFACE'", '"$OPENCONVOY_NETNS_IFACE"')
        return ["sh", "-c", f"exec {cmd}"]

    refused, warned = run_in_netns([in_ns(convoy, 1), in_ns(off, 2)], timeout=60)
    assert refused.returncode == 2, refused.stderr
    lines = refused.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert "V2V authentication is required" in lines[0] and 'auth = "off"' in lines[0]
    assert "openconvoy keys init" in lines[0]
    assert not (tmp_path / "run1").exists()  # refused before anything was made
    # with auth = "off" written, it runs (here: no autopilot answers) and warns once
    warnings = [ln for ln in warned.stderr.splitlines() if "V2V is unauthenticated" in ln]
    assert len(warnings) == 1, warned.stderr
    assert str(off) in warnings[0] and warned.returncode == 1


def test_deploy_without_keys_refuses_and_auth_off_warns(tmp_path, capsys):
    convoy = tmp_path / "lab.toml"
    convoy.write_text('[convoy]\nname = "lab"\n')
    assert main(_deploy(convoy)) == 2
    line = _one_line(capsys)
    assert "holds no convoy keys" in line and 'auth = "off"' in line
    # the operator's abort on such a convoy: the same requirement
    assert main(["abort", "--iface", "lo", "--convoy", str(convoy)]) == 2
    assert "only obeys signed aborts" in _one_line(capsys)


def _keyed(tmp_path, n=3):
    convoy = tmp_path / "lab.toml"
    convoy.write_text('[convoy]\nname = "lab"\n')
    d = ks.default_keys_dir(convoy)
    ks.init_authority(d, "lab", time.time())
    for i in range(n):
        ks.issue_vehicle(d, "lab", i, time.time())
    return convoy, d


def test_key_files_are_refused_as_ssh_does_and_must_be_regular_and_small(tmp_path, capsys):
    convoy, d = _keyed(tmp_path)
    key = d / "vehicle-1.key"
    key.chmod(0o644)  # D56
    assert main(_deploy(convoy)) == 2
    line = _one_line(capsys)
    assert str(key) in line and "accessible by others (mode 0644)" in line and "chmod 600" in line
    key.chmod(0o600)
    d.chmod(0o777)
    assert main(_deploy(convoy)) == 2
    assert "chmod 700" in _one_line(capsys)
    d.chmod(0o700)
    key.unlink()
    key.symlink_to("/dev/zero")  # D57: would be read without end
    assert main(_deploy(convoy)) == 2
    assert "is not a regular file" in _one_line(capsys)
    key.unlink()
    os.mkfifo(key, 0o600)  # a FIFO: refused, never waited on
    assert main(_deploy(convoy)) == 2
    assert "is not a regular file" in _one_line(capsys)
    key.unlink()
    fd = os.open(key, os.O_WRONLY | os.O_CREAT, 0o600)
    os.write(fd, b"x" * (ks.MAX_KEY_FILE_BYTES + 1))
    os.close(fd)
    assert main(_deploy(convoy)) == 2
    assert "larger than any key file" in _one_line(capsys)
    assert stat.S_IMODE(key.stat().st_mode) == 0o600


def test_a_log_that_is_a_device_or_a_fifo_is_one_line(tmp_path, capsys):
    zero = tmp_path / "l.csv"
    zero.symlink_to("/dev/zero")  # D57: MemoryError before
    assert main(["report", str(zero)]) == 2
    assert "not a regular file" in _one_line(capsys)
    fifo = tmp_path / "f.csv"
    os.mkfifo(fifo)  # D57: hung before
    assert main(["report", str(fifo)]) == 2
    assert "not a regular file" in _one_line(capsys)
    zero.unlink()
    assert main(["report", str(tmp_path)]) == 2  # a directory holding only the FIFO
    assert "no OpenConvoy log" in _one_line(capsys)


def test_a_certificate_of_another_vehicle_is_refused(tmp_path, capsys):
    convoy, d = _keyed(tmp_path)
    for ext in ("key", "cert"):  # D60: vehicle 0's pair copied over vehicle 1's
        (d / f"vehicle-1.{ext}").write_bytes((d / f"vehicle-0.{ext}").read_bytes())
    assert main(_deploy(convoy)) == 2
    line = _one_line(capsys)
    assert "'lab.vehicle-0', not vehicle 1's" in line


def test_reissue_needs_force_and_revokes_the_old_certificate(tmp_path, capsys):
    convoy, d = _keyed(tmp_path)
    old = ks.read_certificate(d / "vehicle-1.cert")
    capsys.readouterr()
    assert main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", "1"]) == 2
    assert "already has a key" in _one_line(capsys) and "--force" in "--force"
    assert main(["keys", "issue", "--convoy", str(convoy), "--vehicle-id", "1", "--force"]) == 0
    out = capsys.readouterr().out
    assert "revoked" in out
    assert ks.load_revoked(d) == {old.digest}
    new = ks.load_vehicle(d, 1, time.time())
    assert new.certificate is not None and new.certificate.digest != old.digest
    assert old.digest in new.revoked  # every vehicle loads the list with its credentials


def test_deeply_nested_toml_is_one_line_naming_the_file(tmp_path, capsys):
    p = tmp_path / "deep.toml"
    p.write_text("[convoy]\norigin = " + "[" * 5000 + "]" * 5000 + "\n")  # D58
    assert main(_deploy(p)) == 2
    line = _one_line(capsys)
    assert str(p) in line and "nested" in line


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


def test_an_operator_key_signs_aborts_and_vehicles_obey_it(tmp_path, capsys):
    from openconvoy.comms import legacy_json as cj
    from openconvoy.comms.geodesy import Origin
    from openconvoy.comms.security import certs as c
    from openconvoy.comms.security.auth import Authenticator
    from openconvoy.comms.tempids import TempIds
    from openconvoy.comms.v2v import Receiver

    convoy, d = _keyed(tmp_path)
    assert main(["keys", "operator", "--convoy", str(convoy), "--name", "alice"]) == 0
    assert "lab.operator-alice" in capsys.readouterr().out
    assert main(["keys", "operator", "--convoy", str(convoy), "--name", "alice"]) == 2
    assert "already has a key" in _one_line(capsys)
    now = time.time()
    operator = Authenticator(ks.signer_of_key(d / "operator-alice.key", d, now))
    rx = Receiver(
        TempIds("lab", 3), Origin(0.0, 0.0), 1, auth=Authenticator(ks.load_vehicle(d, 1, now))
    )
    r = rx.handle(operator.sign(cj.make_abort(now), c.PSID_ABORT, now), now + 0.01)
    assert r is not None and r.abort and r.sender == -1
