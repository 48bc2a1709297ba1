"""The three-vehicle demo through each vehicle link, side by side: p95 platooning error and
control-loop overruns through MAVLink, MAVROS on ROS 1 and on ROS 2, AP_DDS (ArduPilot) and
PX4's DDS topics (against the MAVLink demo of PX4 vehicles), on the same scenario and seed,
alternating the links in each round so that the machine's load falls on all of them alike.
Prints one line per run (with the load average) and each link's ratio to its MAVLink
demo's median; the target is within 10 %.

Needs the private network namespace the demo needs, ROS 1 (``make ros1``) and the ROS 2
environment (``make ros2``).

    python benchmarks/bench_demo_ros.py [--duration 30] [--rounds 1]
        [--links mavlink,ros1,ros2,ap-dds,mavlink-px4,px4-dds]
    (also ``v2v-ros2``: the MAVLink demo with its V2V over DDS)
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

LINKS: dict[str, list[str]] = {
    "mavlink": [],
    "ros1": ["--link", "mavros", "--ros", "1"],
    "ros2": ["--link", "mavros", "--ros", "2"],
    "ap-dds": ["--link", "ap-dds"],  # the deploys' nodes Cyclone DDS, the stand-ins rclpy
    "v2v-ros2": ["--v2v", "ros2"],  # MAVLink to the vehicles, V2V on a ROS 2 topic (DDS)
    "mavlink-px4": ["--autopilot", "px4"],
    "px4-dds": ["--autopilot", "px4", "--link", "px4-dds"],
}
BASELINE = {"px4-dds": "mavlink-px4", "mavlink-px4": "mavlink-px4"}
"""Each link's MAVLink demo (same autopilot); ``mavlink`` for the others."""


def loadavg() -> str:
    """The 1, 5 and 15 min load averages."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def run_demo(link: str, duration_s: float, out: Path) -> tuple[float, list[int]]:
    """One demo run: its deploys' p95 platooning error (m) and each deploy's overruns."""
    r = subprocess.run(
        [sys.executable, "-m", "openconvoy.cli", "demo", "--json", "--duration", str(duration_s)]
        + ["--out", str(out), *LINKS[link]],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if r.returncode != 0:
        raise SystemExit(f"demo over {link} failed: {r.stdout[-500:]} {r.stderr[-500:]}")
    p95 = json.loads(r.stdout.strip().splitlines()[-1])["deploy"]["p95_platooning_error_m"]
    overruns = []
    for f in sorted(out.glob("deploy_*.txt")):
        m = re.search(r"(\d+) overruns", f.read_text(errors="replace"))
        overruns.append(int(m.group(1)) if m else -1)
    return float(p95), overruns


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0, help="scenario seconds (30)")
    ap.add_argument("--rounds", type=int, default=1, help="runs of each link (1)")
    ap.add_argument("--links", default="mavlink,ros1,ros2", help="which links, in order")
    a = ap.parse_args()
    links = a.links.split(",")
    bases = {BASELINE.get(k, "mavlink") for k in links}
    if any(k not in LINKS for k in links) or not bases <= set(links):
        print(
            f"--links: from {','.join(LINKS)}, with each one's MAVLink demo "
            "(mavlink; mavlink-px4 for px4-dds)",
            file=sys.stderr,
        )
        return 2
    p95s: dict[str, list[float]] = {k: [] for k in links}
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(a.rounds):
            for link in links:
                before = loadavg()
                p95, overruns = run_demo(link, a.duration, Path(tmp) / f"{link}-{n}")
                p95s[link].append(p95)
                print(
                    f"{link:11s} round {n}: p95 {p95:.3f} m, overruns per deploy {overruns}, "
                    f"load {before} -> {loadavg()}",
                    flush=True,
                )
    for link in links:
        base_name = BASELINE.get(link, "mavlink")
        base = statistics.median(p95s[base_name])
        med = statistics.median(p95s[link])
        print(f"{link:11s} median p95 {med:.3f} m = {med / base:.2f} x {base_name}'s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
