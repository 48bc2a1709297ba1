"""``openconvoy vehicle --sim`` as a process: answers over MAVLink, obeys its signals."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.comms.geodesy import Origin
from openconvoy.testing import free_port, run_for, wait_for


def test_vehicle_process_answers_and_obeys_signals() -> None:
    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "openconvoy.cli",
            "vehicle",
            "--sim",
            "--id",
            "9",
            "--mavlink",
            f"udpin:127.0.0.1:{port}",
            "--autopilot",
            "ardupilot",
            "--home",
            "47.0,8.0,400",
            "--start",
            "10,20,90",
            "--ready-after",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    link = MavlinkLink(
        f"udpout:127.0.0.1:{port}", Origin(47.0, 8.0, 400.0), on_status=lambda line: None
    )
    try:
        ready = proc.stdout.readline()
        assert "vehicle 9" in ready and "ardupilot" in ready
        link.connect(timeout_s=10.0)
        assert link.watch.system_id == 9 and link.autopilot == "ardupilot"
        assert wait_for(lambda: link.inbox.telemetry is not None, 3.0, link)
        state = link.inbox.telemetry.state
        assert abs(state.x - 10.0) < 0.05 and abs(state.y - 20.0) < 0.05
        assert abs(state.heading - 1.5708) < 1e-3
        link.modes.prepare_and_arm(timeout_s=10.0)
        run_for(link, 0.5, speed=0.5, heading=1.5708)
        assert not link.modes.pilot_took_over

        proc.send_signal(signal.SIGUSR1)  # a person flips the mode switch to MANUAL
        assert wait_for(lambda: link.modes.pilot_took_over, 3.0, link)
        assert link.watch.mode == "MANUAL"

        proc.send_signal(signal.SIGUSR2)  # freeze telemetry
        run_for(link, 0.8)
        assert not link.link_ok(time.monotonic())
        proc.send_signal(signal.SIGUSR2)
        assert wait_for(lambda: link.link_ok(time.monotonic()), 3.0, link)

        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5.0) == 0
    finally:
        link.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_vehicle_cli_rejects_bad_arguments() -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "openconvoy.cli",
            "vehicle",
            "--sim",
            "--id",
            "1",
            "--mavlink",
            "udpin:127.0.0.1:1",
            "--home",
            "47.0",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("openconvoy: error: --home")
