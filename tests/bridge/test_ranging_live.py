"""Issue 10, ranging on vehicles, live: deploy runners on simulated MAVLink vehicles, the
follower's vehicle streaming DISTANCE_SENSOR from the in-process ``SimWorld`` (real
MAVLink bytes), the ladder fed by ``DeployRunner._ranging`` as ``sim`` feeds it."""

from __future__ import annotations

import math
import time

import numpy as np
from deploy_harness import make_convoy

from openconvoy.bridge.simvehicle.vehicle import SimVehicle, SimVehicleConfig
from openconvoy.envs.vehicles import VEHICLE_PRESETS, RangingSensor
from openconvoy.logs import read_log
from openconvoy.testing import free_port, wait_until


def _modes_after(log_dir, wall: float) -> tuple[np.ndarray, np.ndarray]:
    log = read_log(log_dir / "vehicle_1.csv")
    t, mode = np.asarray(log["t_s"]), np.asarray(log["mode"])
    return t[t > wall] - wall, mode[t > wall]


def _watch(c, seconds: float, ahead: SimVehicle | None = None) -> list[float]:
    """Centre gaps (m) from the follower to ``ahead`` (default: the leader) every 50 ms."""
    gaps = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        s0 = (ahead or c.cars[0].vehicle).state()
        s1 = c.cars[1].vehicle.state()
        gaps.append(math.hypot(s0.x - s1.x, s0.y - s1.y))
        time.sleep(0.05)
    return gaps


def test_car_without_v2v_cutting_in_is_followed_by_ranging(tmp_path) -> None:
    """A car with no radio stops in the lane 8 m ahead of the follower (centre to centre;
    the leader, heard by V2V, is 15 m ahead): only the rangefinder sees it. The ladder's
    ranging override puts the follower in ``degraded`` and it stops behind the car."""
    c = make_convoy(tmp_path, n=2, policy="paper+ladder", ranging={1: RangingSensor()})
    follower = c.cars[1]
    try:
        wait_until(lambda: follower.vehicle.state().speed > 0.8, 20, "convoy moving")
        s = follower.vehicle.state()
        wall, t_cut = time.time(), time.monotonic()
        p = VEHICLE_PRESETS["1/10"]
        car = SimVehicle(
            f"udpin:127.0.0.1:{free_port()}",
            SimVehicleConfig(
                system_id=9,
                preset=p,
                start_x_m=s.x + 8.0 * math.cos(s.heading),
                start_y_m=s.y + 8.0 * math.sin(s.heading),
                start_heading_rad=s.heading,
            ),
            world=follower.vehicle._world,
        )
        gaps = _watch(c, 1.0, car)
        assert follower.runner.member.mode == "degraded"
        t_rest = wait_until(
            lambda: abs(follower.vehicle.state().speed) < 0.05, 10, "follower at rest"
        )
        gaps += _watch(c, 1.0, car)
        tel = follower.link.inbox.telemetry
        lengths = follower.runner.member.lengths
        assert (
            abs(tel.range_m - (gaps[-1] - 0.5 * (lengths[1] + p.length_m))) < 0.25
        )  # noise 0.05 m
        events = [r for _, r in follower.runner.failsafes.events]
        wall_end = time.time()  # then the test's stop request: the log's last rows say failsafe
    finally:
        c.stop()
    print(f"at rest {t_rest - t_cut:.1f} s after the cut-in, {min(gaps):.2f} m behind it (centre)")
    assert min(gaps) > 5.0  # stopped well clear: 8 m less its braking distance from 1 m/s
    assert events == []  # the ladder did it, not an emergency stop
    t, mode = _modes_after(tmp_path / "run", wall + 0.2)
    assert set(mode[t < wall_end - wall - 0.2]) == {"degraded"}


def test_silent_leader_degrades_then_stops_as_in_sim(tmp_path) -> None:
    """The leader's radio dies and it drives on: the follower, with a rangefinder on the
    leader, goes ``degraded`` after the ladder's 0.5 s and stops after its 2 s (a stale
    target only slows, issue 10: the policy brakes as if the leader braked, ranging can
    only lower that), at rest at a safe gap, with HOLD."""
    c = make_convoy(tmp_path, n=2, policy="paper+ladder", ranging={1: RangingSensor()})
    leader, follower = c.cars
    try:
        wait_until(lambda: follower.vehicle.state().speed > 0.8, 20, "convoy moving")
        wall = time.time()
        leader.v2v.send = lambda state, now: False
        gaps = _watch(c, 1.5)
        assert follower.runner.member.mode == "degraded"
        assert math.isfinite(follower.link.inbox.telemetry.range_m)
        wait_until(lambda: abs(follower.vehicle.state().speed) < 0.05, 10, "follower at rest")
        wait_until(lambda: follower.vehicle.mode == "HOLD", 5, "follower in HOLD")
        events = [r for _, r in follower.runner.failsafes.events]
    finally:
        c.stop()
    assert min(gaps) >= 7.5
    assert events == ["staleness ladder stop"]
    t, mode = _modes_after(tmp_path / "run", wall)
    print(
        "mode changes (s after the radio died):",
        [
            (round(float(t[i]), 2), str(mode[i]))
            for i in range(len(t))
            if i == 0 or mode[i] != mode[i - 1]
        ],
    )
    # Ages run from the last BSM's own time (up to one 0.1 s BSM period before ``wall``).
    first = {m: float(t[mode == m][0]) for m in ("degraded", "failsafe")}
    assert set(mode[t < first["degraded"]]) == {"coop"}
    assert 0.4 <= first["degraded"] <= 0.6 and 1.9 <= first["failsafe"] <= 2.1, first
    assert set(mode[(t >= first["degraded"]) & (t < first["failsafe"])]) == {"degraded"}
    # The ladder's stop is latched by the bridge (stop, then HOLD): logged as ``failsafe``.
    assert set(mode[t >= first["failsafe"]]) == {"failsafe"}
