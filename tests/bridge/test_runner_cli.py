"""``openconvoy deploy``'s assembly from the command line (no message is sent here: the
V2V socket is only opened on loopback; the multicast runs are in the namespace tests)."""

from __future__ import annotations

import time

import pytest

from openconvoy.bridge.deploy import DeployArgs, build_runner
from openconvoy.cli import main
from openconvoy.comms.security import keystore as ks

CONVOY = """\
[convoy]
name = "cli"
vehicles = ["1/10", "1/6", "1/10"]

[safety]
speed_cap_mps = 2.5
min_gap_m = 2.0
"""


@pytest.fixture
def convoy_file(tmp_path):
    p = tmp_path / "convoy.toml"
    p.write_text(CONVOY)
    keys = ks.default_keys_dir(p)  # V2V fails closed: a deploy needs keys (or auth = "off")
    ks.init_authority(keys, "cli", time.time())
    for i in range(3):
        ks.issue_vehicle(keys, "cli", i, time.time())
    return str(p)


def args(convoy: str, **kw) -> DeployArgs:
    base = dict(
        policy="paper",
        vehicle_id=1,
        convoy=convoy,
        mavlink="udpout:127.0.0.1:14999",
        iface="lo",
        quiet=True,
    )
    base.update(kw)
    return DeployArgs(**base)


def test_follower_gets_policy_loss_and_envelope(convoy_file):
    r = build_runner(args(convoy_file, policy="paper+ladder", per=0.3, drop_at="sender", rate=50.0))
    try:
        assert r.member.config.ladder.enabled and r.member.config.topology == "all-predecessors"
        assert r.options.rate_hz == 50.0 and r.leader is None
        meta = r.v2v.metadata
        assert meta["drop_at"] == "sender" and meta["loss"]["per"] == 0.3
        env = r.failsafes.envelope
        assert (env.speed_cap_mps, env.min_gap_m) == (2.5, 2.0)
        assert r.link.url == "udpout:127.0.0.1:14999"
    finally:
        r.v2v.close()


def test_rate_defaults_to_the_policys(convoy_file):
    r = build_runner(args(convoy_file))
    try:
        assert r.options.rate_hz == 20.0
    finally:
        r.v2v.close()


def test_leader_follows_the_convoy_scenario_or_a_track(convoy_file):
    r = build_runner(args(convoy_file, vehicle_id=0))
    try:
        assert r.leader is not None and r.leader.name == "paper" and r.leader_origin is None
    finally:
        r.v2v.close()
    r = build_runner(args(convoy_file, vehicle_id=0, track="example"))
    try:
        assert r.leader.name.startswith("track-file:") and r.leader.name.endswith(
            "example_oval.json"
        )
        assert r.leader_origin is not None  # steered in the track's own frame
    finally:
        r.v2v.close()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--vehicle-id", "3"], "vehicles 0..2"),
        (["--vehicle-id", "1", "--passive"], "passive"),
        (["--vehicle-id", "1", "--policy", "nonsense"], "unknown policy"),
        (["--vehicle-id", "1", "--bag"], "--bag records beside the log: give --log DIR"),
        (["--vehicle-id", "1", "--link", "mavros", "--ros", "3"], "argument --ros"),
        (["--vehicle-id", "1", "--link", "ros"], "argument --link"),
    ],
)
def test_bad_arguments_are_one_line_errors(convoy_file, capsys, extra, message):
    argv = [
        "deploy",
        "--policy",
        "paper",
        "--convoy",
        convoy_file,
        "--mavlink",
        "udpout:127.0.0.1:14999",
        "--iface",
        "lo",
        *extra,
    ]
    # argparse keeps the last --policy/--vehicle-id given
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("openconvoy: error:") and message in err[0]


def test_mavlink_link_needs_a_url(convoy_file, capsys):
    argv = ["deploy", "--policy", "paper", "--convoy", convoy_file, "--iface", "lo"]
    assert main([*argv, "--vehicle-id", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["openconvoy: error: --mavlink URL is required with --link mavlink"]
