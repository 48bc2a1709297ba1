"""One side of the ``--dds-iface`` test, run inside a private network namespace:
``vehicle SECONDS``: a simulated PX4 and its DDS stand-in with DDS on the namespace's
veth; ``link IFACE``: a ``px4-dds`` link with DDS on ``IFACE`` (``--dds-iface``) that
connects, arms into OFFBOARD and drives east (the way it faces) for 3 s; prints one JSON line of what it saw (or that it found no vehicle there).
Each side is its own process, so they meet only through DDS on that interface."""

import json
import sys
import time

from openconvoy.bridge.px4dds.link import Px4DdsLink
from openconvoy.bridge.px4dds.standin import Px4DdsStandIn
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME, SimVehicle, SimVehicleConfig
from openconvoy.comms.netns import IFACE
from openconvoy.core.errors import LinkError


def vehicle(seconds: float) -> None:
    cfg = SimVehicleConfig(autopilot="px4", ready_after_s=0.0, start_x_m=0.0, start_y_m=0.0)
    sim = SimVehicle("udpin:127.0.0.1:14601", cfg).start()
    px4 = Px4DdsStandIn("udpout:127.0.0.1:14601", ns="v1", localhost=False, iface=IFACE).start()
    time.sleep(seconds)
    print(json.dumps({"x": sim.state().x, "mode": sim.mode}), flush=True)
    px4.stop()
    sim.stop()


def link(iface: str) -> None:
    lk = Px4DdsLink("v1", DEFAULT_HOME, 1, iface=iface)
    try:
        lk.connect(15.0 if iface == IFACE else 4.0)
    except LinkError as exc:
        print(json.dumps({"connected": False, "why": str(exc)}))
        return
    lk.modes.prepare_and_arm(15.0)
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        lk.setpoints.send(1.5, 0.0)  # east
        lk.poll()
        time.sleep(0.05)
    tel = lk.poll() or lk._last
    print(
        json.dumps(
            {"connected": True, "armed": bool(tel and tel.armed), "x": tel.state.x if tel else None}
        )
    )
    lk.close()


if __name__ == "__main__":
    vehicle(float(sys.argv[2])) if sys.argv[1] == "vehicle" else link(sys.argv[2])
