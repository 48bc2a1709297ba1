"""Inside a private network namespace: a three-car convoy of deploy runners on simulated
MAVLink vehicles, BSMs over real IPv6 multicast on ``oc0``; then a fault (issue 10):

- ``halt``: the vehicle is switched to HOLD from outside (``SimVehicle.pilot_set_mode``):
  it coasts to rest, its deploy stops commanding and keeps broadcasting;
- ``silent``: its radio dies (``V2V.send`` sends nothing), its deploy keeps driving;
- ``dead``: its deploy dies (the runner thread stops dead, sending nothing at all); the
  autopilot stops the vehicle 3 s after the last setpoint, as ArduPilot does.

Samples every vehicle's true state (from the simulated vehicles) and prints one JSON line:
the smallest centre-to-centre gap, collisions, when each vehicle behind the fault came to
rest, their final modes and failsafe events.

Usage: python netns_fault_driver.py KIND VEHICLE POLICY OUT_DIR [FAULT_AFTER_S]
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.bridge.*

from deploy_harness import make_convoy  # noqa: E402

from openconvoy.comms.geodesy import Origin  # noqa: E402
from openconvoy.comms.tempids import TempIds  # noqa: E402
from openconvoy.comms.v2v import V2V, LinkConfig  # noqa: E402
from openconvoy.testing import wait_until  # noqa: E402

REST_SPEED_MPS = 0.05
WATCH_S = 10.0


def multicast(iface: str):
    def make(i: int, convoy) -> V2V:
        ids = TempIds(convoy.name, convoy.n_vehicles)
        return V2V(LinkConfig.from_v2v(convoy.v2v, iface), ids, Origin(*convoy.origin), i)

    return make


def provoke(convoy, kind: str, v: int) -> threading.Event:
    """Make car ``v`` fail; returns the event that lets a dead runner's thread end."""
    car = convoy.cars[v]
    released = threading.Event()
    if kind == "halt":
        car.vehicle.pilot_set_mode("HOLD")
    elif kind == "silent":
        car.v2v.send = lambda state, now: False
    else:  # dead: nothing more from this deploy, not even a stop or a HOLD

        def dead_tick(now: float) -> str:
            released.wait()
            return "killed"

        car.runner.tick = dead_tick
    return released


def main(kind: str, vehicle: int, policy: str, out: Path, fault_after_s: float) -> dict:
    iface = os.environ.get("OPENCONVOY_NETNS_IFACE", "oc0")
    c = make_convoy(out, n=3, policy=policy, v2v_factory=multicast(iface))
    lengths = [car.runner.member.lengths[i] for i, car in enumerate(c.cars)]
    result: dict = {"kind": kind, "vehicle": vehicle, "policy": policy}
    released = threading.Event()
    try:
        wait_until(lambda: c.cars[2].vehicle.state().speed > 0.5, 30, "convoy moving")
        time.sleep(fault_after_s)
        t_fault = time.monotonic()
        released = provoke(c, kind, vehicle)
        rest: dict[int, float | None] = {j: None for j in range(vehicle + 1, 3)}
        min_gap, collisions = math.inf, 0
        while time.monotonic() - t_fault < WATCH_S + 2.0:
            states = [car.vehicle.state() for car in c.cars]
            now = time.monotonic() - t_fault
            for j in range(1, 3):
                gap = math.hypot(states[j - 1].x - states[j].x, states[j - 1].y - states[j].y)
                min_gap = min(min_gap, gap)
                collisions += gap < 0.5 * (lengths[j] + lengths[j - 1])
            for j in rest:
                if abs(states[j].speed) >= REST_SPEED_MPS:
                    rest[j] = None
                elif rest[j] is None:
                    rest[j] = now
            time.sleep(0.05)
        result.update(
            min_gap_m=min_gap,
            collisions=collisions,
            rest_s=rest,
            speeds=[car.vehicle.state().speed for car in c.cars],
            modes=[car.vehicle.mode for car in c.cars],
            events=[[r for _, r in car.runner.failsafes.events] for car in c.cars],
            msgs_received=[car.v2v.counters.received for car in c.cars],
        )
    except AssertionError as exc:
        result["error"] = str(exc)
    finally:
        released.set()
        c.stop()
    return result


if __name__ == "__main__":
    out = Path(sys.argv[4])
    out.mkdir(parents=True, exist_ok=True)
    after = float(sys.argv[5]) if len(sys.argv) > 5 else 5.0
    print(json.dumps(main(sys.argv[1], int(sys.argv[2]), sys.argv[3], out, after)))
