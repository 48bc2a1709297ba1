"""Inside a private network namespace: two simulated vehicles, two ``openconvoy deploy``
processes (leader + follower) talking BSMs over real IPv6 multicast on ``oc0``; then
``ACTION`` (``sigterm``: SIGTERM to both deploys; ``abort``: ``openconvoy abort``).
Prints one JSON line with what the vehicles received and how the processes ended.

Usage: python netns_deploy_driver.py ACTION OUT_DIR
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from openconvoy.bridge.simvehicle.vehicle import SimVehicle
from openconvoy.comms.geodesy import Origin
from openconvoy.convoy import ConvoyConfig
from openconvoy.demo import (
    deploy_argv,
    sim_vehicle_configs,
    start_local_sim_vehicles,
    stop_convoy,
    write_convoy_toml,
)
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vehicles import vehicle_preset


def main(action: str, out: Path) -> dict:
    iface = os.environ.get("OPENCONVOY_NETNS_IFACE", "oc0")
    names = ("1/10", "1/6")
    origin = ConvoyConfig().origin
    convoy_path = out / "convoy.toml"
    write_convoy_toml(convoy_path, names, origin)
    presets = [vehicle_preset(v) for v in names]
    init = make_scenario("paper", presets=presets).initial_state()
    vehicles, received, procs = [], [], []

    def record_setpoints(v: SimVehicle) -> None:
        """Every setpoint the simulated autopilot receives, with its wall time."""
        log: list[tuple[float, float]] = []
        orig = v.firmware.setpoint

        def record(t, local, frame, mask, vx, vy, yaw, yaw_rate):
            orig(t, local, frame, mask, vx, vy, yaw, yaw_rate)
            log.append((time.time(), math.hypot(vx, vy)))

        v.firmware.setpoint = record
        received.append(log)

    configs = sim_vehicle_configs(init, Origin(*origin), presets, ready_after_s=0.5)
    for i, (v, url) in enumerate(start_local_sim_vehicles(configs, record_setpoints)):
        vehicles.append(v)
        cmd = deploy_argv(i, convoy_path, url, iface, out / "run")
        procs.append(
            subprocess.Popen(
                cmd, stdout=subprocess.DEVNULL, stderr=open(out / f"deploy_{i}.txt", "w")
            )
        )
    result: dict = {"action": action}
    try:
        deadline = time.monotonic() + 40
        while vehicles[1].state().speed < 0.5:
            if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                result["error"] = "follower never moved"
                return result
            time.sleep(0.05)
        if action == "sigterm":
            for p in procs:
                p.send_signal(signal.SIGTERM)
        else:
            subprocess.run(
                # the convoy signs (write_convoy_toml made its keys): so must its operator
                [
                    sys.executable,
                    "-m",
                    "openconvoy.cli",
                    "abort",
                    "--iface",
                    iface,
                    "--convoy",
                    str(convoy_path),
                    "--key",
                    str(convoy_path.with_suffix(".keys") / "authority.key"),
                ],  # fmt: skip
                check=True,
                timeout=20,
            )
        codes = []
        for p in procs:
            try:
                codes.append(p.wait(timeout=15))
            except subprocess.TimeoutExpired:
                codes.append(None)
        time.sleep(1.5)
        # When each deploy detected the event (its metadata, on the shared wall clock).
        metas = [json.loads((out / "run" / f"vehicle_{i}.json").read_text()) for i in range(2)]
        # (a late tick on a loaded machine is an event of its own, not the detection)
        t_det = [
            next(
                e["t_s"]
                for e in m["failsafe_events"]
                if not e["reason"].startswith("control loop late")
            )
            for m in metas
        ]
        result.update(
            exit_codes=codes,
            reasons=[m["exit_reason"] for m in metas],
            events=[m["failsafe_events"] for m in metas],
            modes=[v.mode for v in vehicles],
            speeds=[v.state().speed for v in vehicles],
            log_rows=[sum(1 for _ in open(out / "run" / f"vehicle_{i}.csv")) - 1 for i in range(2)],
            # setpoint speeds each vehicle received more than 0.5 s after the detection
            late_speeds=[[s for ts, s in log if ts > td + 0.5] for log, td in zip(received, t_det)],
            first_after=[
                next(((ts - td, s) for ts, s in log if ts > td), None)
                for log, td in zip(received, t_det)
            ],
        )
    finally:
        stop_convoy(procs, vehicles)
    return result


if __name__ == "__main__":
    out = Path(sys.argv[2])
    out.mkdir(parents=True, exist_ok=True)
    print(json.dumps(main(sys.argv[1], out)))
