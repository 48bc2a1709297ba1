"""What ``deploy`` refuses before arming, and how it ends when stopped while starting:
D59 (``--rate`` lower bound), D64 (a vehicle outside the geofence), D65 (a second deploy of
the same vehicle into the same log), D66 (SIGTERM during startup). Against simulated
autopilots (real MAVLink over localhost UDP) and, for the signal, real deploy processes in
a private network namespace."""

from __future__ import annotations

import socket
import sys
import textwrap
import threading

import pytest
from deploy_harness import make_convoy

from openconvoy.bridge.localv2v import LocalBus, LocalV2V
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.runner import DeployRunner, RunnerOptions
from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.cli import main
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.netns import netns_unavailable_reason, run_in_netns
from openconvoy.convoy import ConvoyConfig
from openconvoy.core.errors import ConfigError
from openconvoy.logs import read_log
from openconvoy.policies import load_policy
from openconvoy.testing import free_port, wait_until


def convoy_toml(tmp_path) -> str:
    path = tmp_path / "c.toml"
    path.write_text('[convoy]\nname = "t"\nvehicles = ["1/10", "1/6"]\n[v2v]\nauth = "off"\n')
    return str(path)


def deploy_argv(tmp_path, *extra: str) -> list[str]:
    return [
        "deploy", "--policy", "paper", "--vehicle-id", "1", "--convoy", convoy_toml(tmp_path),
        "--mavlink", f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}", "--iface", "oc0",
        *extra,
    ]  # fmt: skip


@pytest.mark.parametrize("rate", ["0.05", "1e-9", "4.9"])
def test_a_rate_below_5_hz_is_one_line_and_exit_2(tmp_path, capsys, rate):
    assert main(deploy_argv(tmp_path, "--rate", rate, "--log", str(tmp_path / "run"))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--rate: {rate} is out of range" in err[0]
    assert "[5, 100]" in err[0]
    assert not (tmp_path / "run").exists()
    with pytest.raises(ConfigError, match="5..100 Hz"):
        RunnerOptions(vehicle_id=1, rate_hz=1.0)  # a policy's own control rate, too


def test_a_log_that_holds_this_vehicle_already_is_refused_before_connecting(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "vehicle_1.csv").write_text("t_s,vehicle_id\n")
    assert main(deploy_argv(tmp_path, "--log", str(run))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "vehicle_1.csv exists (another deploy of vehicle 1" in err[0]


def lone_runner(port: int, log_dir, home: Origin | None = None, vehicle_id: int = 1):
    """A deploy runner for one more simulated vehicle (system id 9) on ``port``."""
    cfg = SimVehicleConfig(system_id=9, ready_after_s=0.0, **({"home": home} if home else {}))
    vehicle = SimVehicle(f"udpin:127.0.0.1:{port}", cfg).start()
    convoy = ConvoyConfig(name="test", vehicles=("1/10", "1/6"))
    link = MavlinkLink(f"udpout:127.0.0.1:{port}", Origin(*convoy.origin), vehicle_id=vehicle_id)
    runner = DeployRunner(
        RunnerOptions(vehicle_id=vehicle_id, status_period_s=0.0, connect_timeout_s=5.0),
        convoy,
        load_policy("paper"),
        link,
        LocalV2V(LocalBus()),
        log_dir=log_dir,
        on_status=lambda line: None,
    )
    return vehicle, runner


def run_bounded(runner: DeployRunner, timeout_s: float = 15.0):
    """``runner.run()`` in a thread; a run still going after ``timeout_s`` is stopped and
    fails the test (refusals come at once)."""
    out: list = []
    t = threading.Thread(target=lambda: out.append(runner.run()), daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        runner.request_stop("test over")
        t.join(10.0)
        pytest.fail(f"the run was not refused: still running after {timeout_s} s")
    return out[0]


def test_a_second_deploy_of_a_running_vehicle_into_its_log_is_refused(tmp_path):
    c = make_convoy(tmp_path, n=2)
    vehicle = None
    try:
        first = c.cars[1].runner
        wait_until(lambda: first.timer is not None and first.timer.ticks > 20, 10, "logging")
        home = Origin(*c.convoy.origin)
        vehicle, second = lone_runner(free_port(socket.SOCK_DGRAM), c.log_dir, home)
        lines: list[str] = []
        second.on_status = lines.append
        res = run_bounded(second)
        assert res.exit_code == 2 and "vehicle_1.csv exists" in res.reason
        assert not vehicle.armed and vehicle.setpoints_received == 0  # never armed
        assert any("refused" in line and "vehicle_1.csv exists" in line for line in lines)
    finally:
        c.stop()
        if vehicle is not None:
            vehicle.stop()
    log = read_log(c.log_dir / "vehicle_1.csv")  # one deploy's rows, time going forward
    assert len(log["t_s"]) > 10 and (log["t_s"][1:] > log["t_s"][:-1]).all()


def test_a_vehicle_7500_km_from_the_origin_is_refused_before_arming(tmp_path):
    # The simulated vehicle's default home (52.0, 4.37) against the default convoy origin
    # (28.6, -81.2): D64's repro.
    vehicle, runner = lone_runner(free_port(socket.SOCK_DGRAM), tmp_path / "run")
    try:
        res = run_bounded(runner)
        assert not vehicle.armed
    finally:
        vehicle.stop()
    assert res.exit_code == 2
    assert "vehicle 1 is 7," in res.reason and " km from the convoy's origin" in res.reason
    assert "outside the 200 m geofence" in res.reason
    assert not (tmp_path / "run" / "vehicle_1.csv").exists()


SIGNAL_DRIVER = textwrap.dedent(
    """
    import json, signal, subprocess, sys, time
    argv, delays = json.loads(sys.argv[1]), json.loads(sys.argv[2])
    out = []
    for delay in delays:
        p = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=30)
        out.append({"delay": delay, "rc": p.returncode, "err": err})
    print(json.dumps(out))
    """
)


@pytest.mark.e2e
def test_sigterm_while_starting_exits_0_with_a_line_and_claims_no_log(tmp_path):
    reason = netns_unavailable_reason()
    assert reason is None, f"this test needs a private network namespace: {reason}"
    import json

    log = tmp_path / "run"
    # No vehicle answers: the deploy is importing its modules and opening its sockets
    # (0.5 s; the command line is parsed by ~0.15 s) or waiting for a heartbeat (2.5 s).
    argv = [sys.executable, "-m", "openconvoy.cli", *deploy_argv(tmp_path, "--log", str(log))]
    (r,) = run_in_netns(
        [[sys.executable, "-c", SIGNAL_DRIVER, json.dumps(argv), json.dumps([0.5, 2.5])]],
        timeout=90,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    runs = json.loads(r.stdout.strip().splitlines()[-1])
    for run in runs:
        lines = run["err"].strip().splitlines()
        assert run["rc"] == 0, run
        assert lines and "Traceback" not in run["err"], run
        last = lines[-1]
        assert last.startswith("vehicle 1: ") and "SIGTERM" in last, run
        assert "log in" not in last, run  # no claim of a log that was never created
    assert not (log / "vehicle_1.csv").exists()


def test_deploy_v2v_flag_overrides_the_convoy_files_transport():
    from openconvoy.bridge.deploy import DeployArgs, _v2v_config
    from openconvoy.convoy import ConvoyConfig, V2VConfig

    convoy = ConvoyConfig(vehicles=("1/10", "1/10"), v2v=V2VConfig(ros2_domain=3))
    assert (
        _v2v_config(DeployArgs("paper", 0, "c.toml", None, "oc0"), convoy).transport == "multicast"
    )
    config = _v2v_config(DeployArgs("paper", 0, "c.toml", None, "oc0", v2v="ros2"), convoy)
    assert (config.transport, config.ros2_topic, config.ros2_domain) == (
        "ros2",
        "/openconvoy/v2v",
        3,
    )
