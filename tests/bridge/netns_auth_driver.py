"""Inside a private network namespace: three simulated vehicles and three ``openconvoy
deploy`` processes of a convoy with keys (signed BSMs over real IPv6 multicast on ``oc0``);
once the convoy drives, two forgers claim to be the leader at 50 Hz for 4 s — one without
keys, 1 km ahead; one signing with another convoy's key, at 160 m/s — then an unsigned
``openconvoy abort`` and, 2 s later, a signed one. Prints one JSON line.

Usage: python netns_auth_driver.py OUT_DIR
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.comms.security import keystore as ks
from openconvoy.comms.tempids import TempIds
from openconvoy.convoy import ConvoyConfig
from openconvoy.core import metrics as mt
from openconvoy.demo import (
    deploy_argv,
    sim_vehicle_configs,
    start_local_sim_vehicles,
    stop_convoy,
    write_convoy_toml,
)
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.logs import read_log

CLI = [sys.executable, "-m", "openconvoy.cli"]
FORGED = 200  # frames per forger: 4 s at 50 Hz


def main(out: Path) -> dict:
    iface = os.environ.get("OPENCONVOY_NETNS_IFACE", "oc0")
    names = ("1/10", "1/6", "1/10")
    origin = ConvoyConfig().origin
    convoy_path = out / "convoy.toml"
    write_convoy_toml(convoy_path, names, origin, keys=False)
    keys = out / "convoy.keys"
    now = time.time()
    ks.init_authority(keys, "demo", now)
    for i in range(3):
        ks.issue_vehicle(keys, "demo", i, now)
    foreign = out / "foreign.keys"
    ks.init_authority(foreign, "demo", now)  # same convoy name, another authority
    ks.issue_vehicle(foreign, "demo", 0, now)
    presets = [vehicle_preset(v) for v in names]
    init = make_scenario("paper", presets=presets).initial_state()
    vehicles, procs = [], []
    configs = sim_vehicle_configs(init, Origin(*origin), presets, ready_after_s=0.5)
    for i, (v, url) in enumerate(start_local_sim_vehicles(configs)):
        vehicles.append(v)
        cmd = deploy_argv(
            i, convoy_path, url, iface, out / "run", "--duration", "120"
        )  # the abort ends it
        procs.append(
            subprocess.Popen(
                cmd, stdout=subprocess.DEVNULL, stderr=open(out / f"deploy_{i}.txt", "w")
            )
        )
    result: dict = {}
    try:
        deadline = time.monotonic() + 60
        while vehicles[2].state().speed < 0.5:
            if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                result["error"] = "the convoy never moved"
                return result
            time.sleep(0.05)
        lead = vehicles[0].state()
        lat, lon, _ = enu_to_geodetic(Origin(*origin), lead.x + 1000.0, lead.y)
        leader_id = TempIds("demo", 3).id_of(0).hex()
        send = [
            *CLI,
            "bsm",
            "send",
            "--iface",
            iface,
            "--id",
            leader_id,
            "--rate",
            "50",
            "--count",
            str(FORGED),
            "--lat",
            str(lat),
            "--lon",
            str(lon),
            "--heading",
            "90",
        ]
        t_forge = time.time()
        forgers = [  # both at once
            subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            for argv in (
                [*send, "--speed", "1.5"],
                [*send, "--speed", "160", "--key", str(foreign / "vehicle-0.key")],
            )
        ]
        forger_err = [f.communicate(timeout=30)[1] for f in forgers]
        t_forged = time.time()
        speeds_during = [v.state().speed for v in vehicles]
        subprocess.run([*CLI, "abort", "--iface", iface], check=True, timeout=20)  # unsigned
        time.sleep(2.0)
        running_after_unsigned = [p.poll() is None for p in procs]
        t_abort = time.time()
        signed = subprocess.run(
            [
                *CLI,
                "abort",
                "--iface",
                iface,
                "--convoy",
                str(convoy_path),
                "--key",
                str(keys / "authority.key"),
            ],
            capture_output=True,
            text=True,
            timeout=20,
        )
        result["abort"] = [signed.returncode, signed.stderr[-500:], time.time() - t_abort]
        codes = []
        for p in procs:
            try:
                codes.append(p.wait(timeout=15))
            except subprocess.TimeoutExpired:
                codes.append(None)
        time.sleep(1.0)
        metas = [json.loads((out / "run" / f"vehicle_{i}.json").read_text()) for i in range(3)]
        log = read_log(out / "run")
        t, vid, speed = log["t_s"], log["vehicle_id"], log["speed_mps"]
        during = (t >= t_forge) & (t <= t_forged + 1.0)
        result.update(
            forger_rc=[f.returncode for f in forgers],
            forger_err=[e[-300:] for e in forger_err],
            exit_codes=codes,
            reasons=[m["exit_reason"] for m in metas],
            t_end=[m.get("t_end_s") for m in metas],
            t_forge=t_forge,
            t_abort=t_abort,
            rejected=[m["v2v"]["auth"]["rejected"] for m in metas],
            running_after_unsigned=running_after_unsigned,
            speeds_during=speeds_during,
            max_follower_speed_during=float(speed[during & (vid > 0)].max()),
            metrics=mt.compute_metrics(log),
            modes=[v.mode for v in vehicles],
            final_speeds=[v.state().speed for v in vehicles],
            log_rows=[int((vid == i).sum()) for i in range(3)],
        )
    finally:
        stop_convoy(procs, vehicles)
    return result


if __name__ == "__main__":
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    print(json.dumps(main(out), default=float))
