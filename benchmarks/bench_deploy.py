"""Deploy loop timing against simulated MAVLink vehicles: period jitter and latency.

Two processes, as on a real convoy where each vehicle runs its own ``deploy``: a helper
process runs two simulated ArduPilot vehicles and the leader's ``DeployRunner``; this
process runs the follower's ``DeployRunner`` (the ``paper`` policy), the one measured. Each
drives its vehicle over real MAVLink (UDP on localhost); the two runners exchange real
J2735 BSMs (``comms.v2v.V2V``: UPER encode/decode, temporary IDs) over a UDP unicast pair
on loopback (multicast is not needed to time the loop, and loopback cannot carry IPv6
multicast). At 20 Hz and at 50 Hz it reports, for the follower's loop (telemetry, member,
BSM send/receive, observation, policy, ladder, failsafes, setpoint, log row):

- loop period jitter: |actual tick period - nominal|, p50 and p99 (ms);
- telemetry-in -> setpoint-out latency: from the simulated autopilot sending the newest
  position/attitude message the tick used to the setpoint leaving (ms, p50/p99); on
  loopback the transit is microseconds, so this is the wait for the next tick plus the
  work (with telemetry at rate R and the loop at rate R, half a period on average);
- compute: telemetry read -> setpoint sent within one tick (ms, p50/p99);
- overruns, and the telemetry rate the simulated autopilot accepted (it refuses rates
  above 40 Hz, as ArduPilot refuses rates above its loop rate, and the link lowers the
  request).

Prints one JSON object. Usage: ``python benchmarks/bench_deploy.py [--seconds S]
[--policy SPEC]`` (``--policy paper-mpc``: the follower runs the MPC, as in ``docs/mpc.md``).
"""

from __future__ import annotations

import argparse
import json
import platform
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.runner import DeployRunner, RunnerOptions
from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.comms.geodesy import Origin
from openconvoy.comms.multicast import Datagram
from openconvoy.comms.tempids import TempIds
from openconvoy.comms.v2v import V2V, LinkConfig
from openconvoy.convoy import ConvoyConfig
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.policies import load_policy
from openconvoy.testing import free_port

CONVOY = ConvoyConfig(name="bench", vehicles=("1/10", "1/6"))
POLICY = ["paper"]
"""The follower's policy spec (``--policy``)."""


class UdpPair:
    """A ``comms.multicast.Transport`` over loopback unicast: bound to ``port``, sending to
    ``peer``. Non-blocking."""

    def __init__(self, port: int, peer: int) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", port))
        self._sock.setblocking(False)
        self._peer = ("127.0.0.1", peer)

    def send(self, data: bytes) -> None:
        self._sock.sendto(data, self._peer)

    def recv_all(self, max_batch: int = 10_000) -> list[Datagram]:
        out: list[Datagram] = []
        while len(out) < max_batch:
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, ConnectionRefusedError):
                return out
            out.append(Datagram(data, addr[0]))
        return out

    def close(self) -> None:
        self._sock.close()


def _runner(
    i: int, rate_hz: float, seconds: float, mav_port: int, v2v_port: int, peer: int, log_dir: Path
) -> DeployRunner:
    origin = Origin(*CONVOY.origin)
    presets = [vehicle_preset(v) for v in CONVOY.vehicles]
    v2v = V2V(
        LinkConfig(iface="lo"),
        TempIds(CONVOY.name, 2),
        origin,
        i,
        transport=UdpPair(v2v_port, peer),
    )
    link = MavlinkLink(
        f"udpout:127.0.0.1:{mav_port}",
        origin,
        vehicle_id=i,
        telemetry_hz=rate_hz,
        on_status=lambda line: None,
    )
    return DeployRunner(
        RunnerOptions(
            vehicle_id=i, rate_hz=rate_hz, duration_s=seconds, status_period_s=0, record_timing=True
        ),
        CONVOY,
        load_policy(POLICY[0]),
        link,
        v2v,
        leader=make_scenario("paper", presets=presets) if i == 0 else None,
        lengths=[p.length_m for p in presets],
        log_dir=log_dir,
        on_status=lambda line: None,
    )


def child(spec: dict) -> int:
    """The helper process: both vehicles and the leader; notes telemetry send times of the
    follower's vehicle (monotonic clock, system-wide on Linux)."""
    origin = Origin(*CONVOY.origin)
    presets = [vehicle_preset(v) for v in CONVOY.vehicles]
    init = make_scenario("paper", presets=presets).initial_state()
    vehicles, sent = [], []
    for i in range(2):
        cfg = SimVehicleConfig(
            system_id=i + 1,
            preset=presets[i],
            home=origin,
            start_x_m=float(init.x[i]),
            start_y_m=float(init.y[i]),
            ready_after_s=0.0,
        )
        v = SimVehicle(f"udpin:127.0.0.1:{spec['mav'][i]}", cfg)
        if i == 1:
            orig = v._streams.send_telemetry

            def send(mav, msg_id, t, orig=orig):
                orig(mav, msg_id, t)
                if msg_id in (33, 30):  # GLOBAL_POSITION_INT, ATTITUDE
                    sent.append(time.monotonic())

            v._streams.send_telemetry = send
        vehicles.append(v.start())
    print("ready", flush=True)
    leader = _runner(
        0,
        spec["rate"],
        spec["seconds"],
        spec["mav"][0],
        spec["v2v"][0],
        spec["v2v"][1],
        Path(spec["dir"]) / "leader",
    )
    leader.run()
    sys.stdin.readline()  # until the follower is done
    for v in vehicles:
        v.stop()
    Path(spec["times"]).write_text(json.dumps(sent))
    return 0


def _pct(a: np.ndarray, q: float) -> float:
    return round(float(np.percentile(a, q)) * 1e3, 3) if len(a) else float("nan")


def measure(rate_hz: float, seconds: float) -> dict:
    """The follower's loop timing at ``rate_hz`` for ``seconds`` of driving."""
    with tempfile.TemporaryDirectory() as tmp:
        spec = {
            "rate": rate_hz,
            "seconds": seconds,
            "mav": [free_port(), free_port()],
            "v2v": [free_port(), free_port()],
            "dir": tmp,
            "times": str(Path(tmp) / "times.json"),
        }
        proc = subprocess.Popen(
            [sys.executable, __file__, "--child", json.dumps(spec)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert proc.stdout.readline().strip() == "ready"
            follower = _runner(
                1,
                rate_hz,
                seconds,
                spec["mav"][1],
                spec["v2v"][1],
                spec["v2v"][0],
                Path(tmp) / "follower",
            )
            result = follower.run()
            proc.stdin.write("\n")
            proc.stdin.flush()
            proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
        sent_times = np.array(json.loads(Path(spec["times"]).read_text()))
    t_start = (
        follower.start_gate.t_start
        if follower.start_gate.t_start is not None
        else follower.timings[0].t_tick
    )
    timings = [t for t in follower.timings if t.t_tick >= t_start]  # driving only
    periods = np.diff(np.array([t.t_tick for t in timings]))
    jitter = np.abs(periods - 1.0 / rate_hz)
    lat, comp = [], []
    for t in timings:
        if not np.isfinite(t.t_sent):
            continue
        k = int(np.searchsorted(sent_times, t.t_polled, side="right")) - 1
        if k >= 0:
            lat.append(t.t_sent - sent_times[k])
        comp.append(t.t_sent - t.t_polled)
    return {
        "rate_hz": rate_hz,
        "ticks": len(timings),
        "period_ms_p50": _pct(periods, 50),
        "jitter_ms_p50": _pct(jitter, 50),
        "jitter_ms_p99": _pct(jitter, 99),
        "latency_ms_p50": _pct(np.array(lat), 50),
        "latency_ms_p99": _pct(np.array(lat), 99),
        "compute_ms_p50": _pct(np.array(comp), 50),
        "compute_ms_p99": _pct(np.array(comp), 99),
        "overruns": result.overruns,
        "msgs_received": follower.member.msgs_received,
        "telemetry_hz_accepted": follower.link.telemetry_rates,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--seconds", type=float, default=10.0, help="driving time per rate (default 10)"
    )
    ap.add_argument("--policy", default="paper", help="the follower's policy (default paper)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    POLICY[0] = args.policy
    if args.child:
        return child(json.loads(args.child))
    out = {
        "benchmark": "deploy_loop",
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": len(__import__("os").sched_getaffinity(0)),
        "policy": args.policy,
        "load_average": __import__("os").getloadavg(),
        "results": [measure(rate, args.seconds) for rate in (20.0, 50.0)],
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
