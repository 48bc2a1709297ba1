"""How a deploy ends (issue 22 item 3, issue 27 item 4), against simulated autopilots
(``bridge.simvehicle``: real MAVLink bytes over localhost UDP/TCP through pymavlink).

- a run stopped while driving brakes to rest logging and broadcasting, then HOLD and
  disarm (``stay_armed`` keeps it armed in HOLD);
- PX4's Hold drifting (the firmware's loops around its hold point) is reported while the
  deploy still holds the vehicle, which it then disarms;
- PX4's offboard-loss failsafe after a pause of the loop is a failsafe (exit 1), its text
  not lost to a full socket buffer;
- after the autopilot's death: rows marked invalid (not the last position repeated),
  ``report`` leaves them out and says how many, the metadata names the autopilot, the
  exit line says why HOLD was not sent.
"""

from __future__ import annotations

import json
import logging
import threading
import time

import numpy as np
import pytest
from deploy_harness import make_convoy

from openconvoy.bridge.vehicle import HOLD_BELOW_MPS, REST_MPS, brake_time_s
from openconvoy.logs import read_log, read_log_counted
from openconvoy.testing import wait_until


def moving(car, speed: float = 0.8) -> bool:
    return car.vehicle.state().speed > speed


def statuses(car) -> list[str]:
    lines: list[str] = []
    car.runner.on_status = lines.append
    return lines


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_a_signal_while_driving_brakes_to_rest_logged_and_broadcast_then_disarms(
    tmp_path, autopilot
):
    c = make_convoy(tmp_path, n=2, autopilot=autopilot)
    leader, follower = c.cars
    lines = statuses(leader)
    try:
        wait_until(lambda: moving(leader) and moving(follower), 20, "convoy moving")
        t_stop = time.time()
        sent_before = leader.runner.member.msgs_sent
        leader.runner.request_stop("SIGTERM")
        res = leader.join(12.0)
        armed = leader.vehicle.armed
        v_true = leader.vehicle.state().speed
        wait_until(lambda: abs(leader.vehicle.state().speed) < 0.05, 3.0, "at rest")
    finally:
        c.stop()
    assert (res.exit_code, res.reason) == (0, "SIGTERM")
    assert abs(v_true) < 0.3 and not armed  # (nearly) at rest and disarmed when it exits
    assert "vehicle 0: at rest in HOLD, disarmed" in lines
    log = read_log(c.log_dir / "vehicle_0.csv")
    t, v = log["t_s"], log["speed_mps"]
    after = t >= t_stop
    # The braking is in the log, down to rest (it used to end at the speed of the signal).
    # The loop ends on the telemetry that shows less than HOLD_BELOW_MPS, after the tick
    # that logged its row (so the last row may read one telemetry step faster), or when
    # the braking time has run out, slower than REST_MPS: HOLD stops the rest (v_true).
    assert after.sum() >= 5 and v[after][0] > 0.5
    braking_s = t[-1] - t[after][0]
    assert abs(v[-1]) <= 2 * HOLD_BELOW_MPS or (
        braking_s >= brake_time_s(v[after][0]) - 0.2 and abs(v[-1]) < REST_MPS
    ), (v[-1], braking_s)
    assert set(log["mode"][after].tolist()) == {"failsafe"}
    # ... and was broadcast: the followers saw it stop.
    assert leader.runner.member.msgs_sent > sent_before + 3
    assert log["msgs_sent"][-1] > log["msgs_sent"][after][0]


def test_stay_armed_leaves_the_vehicle_armed_in_hold(tmp_path):
    c = make_convoy(tmp_path, n=2, options={0: {"stay_armed": True, "duration_s": 2.0}})
    lines = statuses(c.cars[0])
    try:
        res = c.cars[0].join(20.0)
        mode, armed = c.cars[0].vehicle.mode, c.cars[0].vehicle.armed
    finally:
        c.stop()
    assert res.exit_code == 0 and res.reason == "duration reached"
    assert mode == "HOLD" and armed
    assert any("left ARMED in HOLD (--stay-armed)" in line for line in lines)
    meta = json.loads((c.log_dir / "vehicle_0.json").read_text())
    assert meta["stay_armed"] is True and meta["uncommanded_motion"] is None


def test_px4_hold_drift_is_reported_and_the_held_vehicle_disarmed(tmp_path):
    """PX4's Hold drives back to its hold point as its drifting estimate sees it: the
    firmware's loops around the hold point (issue 22, PX4 HOLD)."""
    c = make_convoy(tmp_path, n=2, autopilot="px4", vehicle_config={"hold_drift_mps": 0.5})
    leader, follower = c.cars
    lines = statuses(follower)
    try:
        wait_until(lambda: moving(follower), 20, "follower moving")
        leader.runner.request_stop("SIGTERM")  # the leader goes quiet: the follower latches
        wait_until(lambda: follower.vehicle.mode == "LOITER", 8, "follower held (Hold)")
        wait_until(lambda: follower.runner.vehicle.uncommanded, 12, "uncommanded motion seen")
        wait_until(lambda: not follower.vehicle.armed, 3, "disarmed")
        seen = follower.runner.vehicle.uncommanded
    finally:
        c.stop()
    res = follower.join(1.0)
    assert seen.startswith("uncommanded motion in LOITER")
    assert any(
        "WARNING: uncommanded motion in LOITER" in ln and "disarming it" in ln for ln in lines
    )
    assert res.exit_code == 1
    meta = json.loads((c.log_dir / "vehicle_1.json").read_text())
    assert meta["uncommanded_motion"] == seen
    assert seen in [e["reason"] for e in meta["failsafe_events"]]


def test_px4_offboard_loss_after_a_loop_pause_is_a_failsafe(tmp_path):
    """A 2.5 s pause of the loop: PX4 leaves OFFBOARD for POSCTL with "Failsafe activated"
    (shared/sitl-px4 row 16) while ~200 messages/s fill the socket buffer; the deploy
    must still call it the autopilot's failsafe and exit 1 (it said "pilot took over ...
    not this link" and exited 0 on the firmware)."""
    stall = threading.Event()
    c = make_convoy(
        tmp_path, n=2, autopilot="px4", start=False, vehicle_config={"other_streams_hz": 600.0}
    )
    follower = c.cars[1]
    real_sleep = follower.runner.sleep

    def sleep(s: float) -> None:
        if stall.is_set():
            stall.clear()
            real_sleep(2.5)
        real_sleep(s)

    follower.runner.sleep = sleep
    for car in c.cars:
        car.start()
    try:
        wait_until(lambda: moving(follower), 20, "follower moving")
        stall.set()
        wait_until(lambda: follower.runner.failsafes.took_over, 8, "runner sees POSCTL")
        reason = follower.link.modes.takeover_reason
        texts = follower.link.watch.status_texts
    finally:
        c.stop()
    res = follower.join(1.0)
    assert "to POSCTL, set by the autopilot's failsafe ('Failsafe activated')" in reason
    assert "Failsafe activated" in texts
    assert res.exit_code == 1


def test_after_the_autopilot_dies_rows_are_invalid_and_the_metadata_names_it(
    tmp_path, caplog, capsys
):
    c = make_convoy(tmp_path, n=2, tcp=True)
    leader, follower = c.cars
    lines = statuses(leader)
    caplog.set_level(logging.WARNING)
    try:
        wait_until(lambda: moving(leader), 20, "leader moving")
        leader.vehicle.stop()  # the autopilot process dies: EOF on its TCP link
        t_dead = time.time()
        wait_until(lambda: leader.link.lost, 3, "EOF seen")
        time.sleep(1.5)
        leader.runner.request_stop("SIGTERM")
        res = leader.join(10.0)
    finally:
        c.stop()
    assert res.exit_code == 1  # the autopilot link was lost
    raw = np.genfromtxt(c.log_dir / "vehicle_0.csv", delimiter=",", names=True, dtype=None)
    invalid = raw["telemetry_valid"] == 0
    assert invalid.sum() >= 20  # ~1.5 s at 20 Hz without telemetry
    assert np.isnan(raw["x_m"][invalid]).all() and np.isnan(raw["speed_mps"][invalid]).all()
    assert (raw["t_s"][invalid] > t_dead - 0.6).all()  # only after the death (+ the timeout)
    log, left_out = read_log_counted(c.log_dir)
    assert left_out == {0: int(invalid.sum())}
    assert np.isfinite(log["x_m"]).all()
    meta = json.loads((c.log_dir / "vehicle_0.json").read_text())
    assert meta["autopilot"] == "ardupilot"  # was null after the link's reset
    assert not any("not identified" in r.getMessage() for r in caplog.records)
    assert any("HOLD and disarm at exit not sent: the autopilot link is lost" in ln for ln in lines)
    # report leaves the rows out and says how many
    from openconvoy.cli import main

    assert main(["report", str(c.log_dir)]) == 0
    out = capsys.readouterr().out
    assert f"left out {int(invalid.sum())} rows written without telemetry" in out


def test_delivery_ratio_is_over_the_followers_lossy_links(tmp_path):
    """Followers at PER 0.5, the leader lossless (as the firmware runs with ``--per``
    on the followers only): the run's delivery ratio is the followers' (it was 0.803
    against their 0.70-0.71 with the leader's 100 % counted)."""
    from openconvoy.bridge.localv2v import LocalBus, LocalV2V
    from openconvoy.comms.loss import LossConfig
    from openconvoy.core.metrics import compute_metrics

    bus = LocalBus()

    def v2v(i, convoy):
        return LocalV2V(bus, loss=LossConfig(per=0.5), seed=i) if i > 0 else LocalV2V(bus)

    c = make_convoy(tmp_path, n=3, v2v_factory=v2v)
    try:
        time.sleep(6.0)
    finally:
        c.stop()
    log = read_log(c.log_dir)
    metas = [json.loads((c.log_dir / f"vehicle_{i}.json").read_text()) for i in range(3)]
    rec = sum(m["msgs_received"] for m in metas[1:])
    lost = sum(m["msgs_lost"] for m in metas[1:])
    assert rec > 50 and lost > 50 and metas[0]["msgs_lost"] == 0
    leader_rows = log["vehicle_id"] == 0
    assert (log["msgs_received"][leader_rows] == -1).all()  # lossless: not counted
    ratio = compute_metrics(log)["delivery_ratio"]
    assert ratio == pytest.approx(rec / (rec + lost), abs=0.02)
    assert 0.4 < ratio < 0.6
    # per follower, in report's metrics.json
    from openconvoy.cli import main

    assert main(["report", str(c.log_dir)]) == 0
    per = json.loads((c.log_dir / "metrics.json").read_text())["per_follower"]
    for i in (1, 2):
        own = metas[i]["msgs_received"] / (metas[i]["msgs_received"] + metas[i]["msgs_lost"])
        assert per[str(i)]["delivery_ratio"] == pytest.approx(own, abs=0.02)
    assert "0" not in per
