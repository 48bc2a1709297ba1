"""A datagram flood against deployed vehicles: does the control loop keep its rate?

Inside a private network namespace (``comms.netns``; nothing leaves the machine): simulated
ArduPilot vehicles (``bridge.simvehicle.vehicle``, real MAVLink over loopback UDP) driven by real
``openconvoy deploy`` processes exchanging J2735 BSMs over real IPv6 multicast, while a
separate process sends valid BSMs from a foreign temporary id to the convoy's group at
``--rate`` per second for ``--flood-s`` seconds (the flood that once dropped every deploy
from 20 Hz to 2-3 Hz with gaps up to 3.7 s). From each vehicle's log and run metadata,
over the flood's window:

- ticks on time: share of intervals between consecutive log rows (one per tick) within
  half a period of the nominal period;
- the largest interval between ticks, seconds and periods;
- overruns (scheduled ticks missed) and late ticks (more than 2 periods late, a failsafe
  event), over the whole run;
- the V2V counters (foreign datagrams are ``filtered``; ``budget_hits``: ticks whose
  receive time budget ran out).

Prints one JSON object. Usage::

    python benchmarks/bench_flood.py [--vehicles 3] [--rate 40000] [--flood-s 10]

``--vehicles 1`` runs a single follower (``--dry-run``, waiting for a leader that never
comes: its loop ticks all the same), the cheap form the test uses.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

FOREIGN_ID = b"\xf0\x0d\xf0\x0d"


def flood(iface: str, group: str, port: int, rate: float, seconds: float) -> dict:
    """Send valid BSM frames from ``FOREIGN_ID`` at ``rate`` per second for ``seconds``:
    how many, and the flood's start and end (wall clock, s). Frames are encoded once (128
    msgCnt values), then replayed."""
    from openconvoy.comms import bsm as j
    from openconvoy.comms.geodesy import Origin
    from openconvoy.comms.mapping import state_to_core
    from openconvoy.comms.multicast import Ipv6Multicast
    from openconvoy.core.state import VehicleState

    origin = Origin(28.6024, -81.2001, 0.0)
    frames = [
        j.encode_frame(
            state_to_core(VehicleState(0, time.time(), 5.0, 0.0, 2.0, 0.0), origin, FOREIGN_ID, k)
        )
        for k in range(128)
    ]
    sock = Ipv6Multicast(iface, group, port, loop=True)
    wall0 = time.time()
    t0 = time.monotonic()
    sent = 0
    try:
        while True:
            now = time.monotonic()
            if now - t0 >= seconds:
                break
            due = int((now - t0) * rate)
            while sent < due:
                try:
                    sock.send(frames[sent & 127])
                except OSError:  # a full send buffer: that datagram is simply not sent
                    pass
                sent += 1
            time.sleep(0.0005)
    finally:
        sock.close()
    return {"sent": sent, "t0": wall0, "t1": wall0 + time.monotonic() - t0}


def tick_stats(t_s: list[float], period: float) -> dict:
    """Ticks on time and the largest gap from a log's row times (s)."""
    gaps = [b - a for a, b in zip(t_s, t_s[1:])]
    if not gaps:
        return {
            "ticks": len(t_s),
            "on_time": math.nan,
            "max_gap_s": math.nan,
            "max_gap_periods": math.nan,
        }
    on_time = sum(1 for g in gaps if abs(g - period) <= 0.5 * period) / len(gaps)
    return {
        "ticks": len(t_s),
        "expected_ticks": round((t_s[-1] - t_s[0]) / period) + 1,
        "on_time": on_time,
        "max_gap_s": max(gaps),
        "max_gap_periods": max(gaps) / period,
    }


def _rows(csv_path: Path, t0: float, t1: float) -> list[float]:
    import csv

    with open(csv_path, newline="") as f:
        return [t for t in (float(r["t_s"]) for r in csv.DictReader(f)) if t0 <= t <= t1]


def inside(args: argparse.Namespace) -> dict:
    """The inside half: vehicles, deploys, flood, figures."""
    import tempfile

    from openconvoy.comms import netns
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

    iface = (
        netns.setup_network()
        if os.environ.get(netns.ENV_IFACE) is None
        else os.environ[netns.ENV_IFACE]
    )
    out = Path(args.out or tempfile.mkdtemp(prefix="openconvoy-flood-"))
    out.mkdir(parents=True, exist_ok=True)
    defaults = ConvoyConfig()
    names = defaults.vehicles if args.vehicles > 1 else defaults.vehicles[:2]
    names = names[: max(args.vehicles, 2)]
    convoy_path = out / "convoy.toml"
    write_convoy_toml(convoy_path, tuple(names), defaults.origin)
    presets = [vehicle_preset(v) for v in names]
    init = make_scenario("paper", presets=presets).initial_state()
    ids = list(range(len(names))) if args.vehicles > 1 else [1]
    vehicles, procs, errs = [], [], []
    period = 1.0 / args.loop_hz
    result: dict = {
        "vehicles": len(ids),
        "rate_per_s": args.rate,
        "flood_s": args.flood_s,
        "loop_hz": args.loop_hz,
        "cpus": os.cpu_count(),
    }
    try:
        origin = Origin(*defaults.origin)
        configs = sim_vehicle_configs(init, origin, presets, ids, ready_after_s=0.5)
        for i, (vehicle, url) in zip(ids, start_local_sim_vehicles(configs)):
            vehicles.append(vehicle)
            cmd = deploy_argv(
                i, convoy_path, url, iface, out / "run",
                "--rate", repr(args.loop_hz), "--quiet",
            )  # fmt: skip
            if args.vehicles == 1:
                cmd.append("--dry-run")
            errs.append(open(out / f"deploy_{i}.txt", "w"))
            procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errs[-1]))
        # Flood once the convoy runs: the last follower moving (or, alone, logging).
        deadline = time.monotonic() + 60
        last_csv = out / "run" / f"vehicle_{ids[-1]}.csv"
        while True:
            if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                result["error"] = "the convoy never got going"
                return result
            if args.vehicles == 1:
                if last_csv.exists() and sum(1 for _ in open(last_csv)) > 20:
                    break
            elif vehicles[-1].state().speed > 0.3:
                break
            time.sleep(0.05)
        flooder = subprocess.run(
            [
                sys.executable,
                __file__,
                "--flood-only",
                "--iface",
                iface,
                "--rate",
                repr(args.rate),
                "--flood-s",
                repr(args.flood_s),
            ],
            capture_output=True,
            text=True,
            timeout=args.flood_s + 60,
        )
        if flooder.returncode != 0:
            result["error"] = f"flood failed: {flooder.stderr[-2000:]}"
            return result
        sent = json.loads(flooder.stdout.strip().splitlines()[-1])
        t0, t1 = sent["t0"], sent["t1"]
        result["flood_sent"] = sent["sent"]
        result["flood_rate_achieved_per_s"] = sent["sent"] / (t1 - t0)
        result["moving_at_end"] = [round(v.state().speed, 3) for v in vehicles]
    finally:
        result["exit_codes"] = stop_convoy(procs, vehicles)
        for f in errs:
            f.close()
    per_vehicle = {}
    for i in ids:
        meta = json.loads((out / "run" / f"vehicle_{i}.json").read_text())
        stats = tick_stats(_rows(out / "run" / f"vehicle_{i}.csv", t0, t1), period)
        counters = meta.get("v2v_counters") or {}
        stats.update(
            overruns=meta["overruns"],
            late_ticks=meta.get("late_ticks"),
            max_tick_late_s=meta.get("max_tick_late_s"),
            run_ticks=meta["ticks"],
            filtered=counters.get("filtered"),
            received=counters.get("received"),
            budget_hits=counters.get("budget_hits"),
            late_events=sum(
                1 for e in meta["failsafe_events"] if e["reason"].startswith("control loop late")
            ),
        )
        per_vehicle[str(i)] = stats
    result["per_vehicle"] = per_vehicle
    result["on_time_min"] = min(s["on_time"] for s in per_vehicle.values())
    result["max_gap_periods"] = max(s["max_gap_periods"] for s in per_vehicle.values())
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--vehicles", type=int, default=3, choices=(1, 2, 3))
    ap.add_argument("--rate", type=float, default=40_000.0, help="foreign BSMs per second")
    ap.add_argument("--flood-s", type=float, default=10.0)
    ap.add_argument("--loop-hz", type=float, default=20.0)
    ap.add_argument("--out", help="keep the run here (default: a temporary directory)")
    ap.add_argument("--iface", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--flood-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.flood_only:
        print(json.dumps(flood(args.iface, "ff15::4f43", 4200, args.rate, args.flood_s)))
        return
    if args.inside:
        print(json.dumps(inside(args)))
        return
    from openconvoy.comms.netns import require_netns

    require_netns()
    argv = [
        sys.executable,
        __file__,
        "--inside",
        "--vehicles",
        str(args.vehicles),
        "--rate",
        repr(args.rate),
        "--flood-s",
        repr(args.flood_s),
        "--loop-hz",
        repr(args.loop_hz),
    ]
    if args.out:
        argv += ["--out", str(Path(args.out).resolve())]
    r = subprocess.run(
        ["unshare", "-rn", *argv], capture_output=True, text=True, timeout=args.flood_s + 180
    )
    if r.returncode != 0:
        sys.exit(f"bench_flood failed: {r.stderr[-3000:]}")
    print(r.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
