"""What ``MavlinkLink`` puts on the wire and how it reads it, checked on real MAVLink bytes
against a scripted autopilot (``mavlink_edge``) and against the firmware recordings in
shared/sitl/ (ArduPilot Rover 4.7) and shared/sitl-px4/ (PX4 SIH rover)."""

from __future__ import annotations

import gzip
import json
import math
import time
from pathlib import Path

import pytest
from mavlink_edge import EdgeAutopilot

from openconvoy.bridge.link import ModeLost
from openconvoy.bridge.mavlink.link import MavlinkLink
from openconvoy.bridge.simvehicle.vehicle import DEFAULT_HOME
from openconvoy.testing import wait_for

DATA = Path(__file__).resolve().parents[1] / "data"  # tests/data: see its README
FLT_EPSILON = 1.1920929e-07  # ArduPilot's is_negative(x): x <= -FLT_EPSILON
COMPASS = (0.0, 45.0, 89.99, 90.0, 90.01, 135.0, 180.0, 225.0, 270.0, 315.0)


def enu(compass_deg: float) -> float:
    """Compass degrees (0 north, clockwise) -> ENU heading, rad."""
    return math.radians(90.0 - compass_deg)


def same_angle(a: float, b: float, tol: float = 1e-6) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) <= tol


@pytest.fixture
def edge():
    made: list[tuple[EdgeAutopilot, MavlinkLink]] = []

    def make(
        connect: bool = True, link_kwargs: dict | None = None, **kw
    ) -> tuple[EdgeAutopilot, MavlinkLink, list[str]]:
        ap = EdgeAutopilot(**kw).start()
        lines: list[str] = []
        link = MavlinkLink(ap.url, DEFAULT_HOME, on_status=lines.append, **(link_kwargs or {}))
        made.append((ap, link))
        if connect:
            link.connect(timeout_s=5.0)
            assert wait_for(lambda: link.inbox.telemetry is not None, 2.0, link)
        return ap, link, lines

    yield make
    for ap, link in made:
        link.close()
        ap.stop()


def sent_setpoint(ap: EdgeAutopilot, kind: str, link: MavlinkLink):
    assert wait_for(lambda: ap.messages(kind), 1.0, link), f"no {kind} arrived"
    msg = ap.messages(kind)[-1]
    ap.clear()
    return msg


def test_ardupilot_setpoints_are_body_forward_in_every_quadrant(edge):
    ap, link, _ = edge(autopilot="ardupilot")
    for compass in COMPASS:
        assert link.setpoints.send(1.5, enu(compass))
        m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
        assert (m.type_mask, m.coordinate_frame) == (
            2503,
            6,
        )  # velocity + yaw, GLOBAL_RELATIVE_ALT_INT
        assert m.vx == 1.5 and m.vy == 0.0, compass  # body-forward speed, never a NED vector
        assert m.vx > -FLT_EPSILON  # Rover reverses on is_negative(vx) alone: never here
        assert same_angle(m.yaw, math.radians(compass)), compass  # absolute yaw, NED
    # Reverse only when a negative speed is asked for.
    link.setpoints.send(-0.5, enu(135.0))
    m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
    assert m.vx == -0.5 and m.vy == 0.0 and same_angle(m.yaw, math.radians(135.0))


def test_ardupilot_stop_is_speed_zero_with_yaw_at_the_current_heading(edge):
    ap, link, _ = edge(autopilot="ardupilot", heading_deg=135.0)
    assert link.setpoints.stop()
    m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
    assert m.type_mask == 2503  # never the zero velocity-only setpoint ("heading north")
    assert m.vx == 0.0 and math.copysign(1.0, m.vx) == 1.0 and m.vy == 0.0  # +0.0, not -0.0
    assert same_angle(m.yaw, math.radians(135.0), 1e-4)
    # A -0.0 commanded speed is a stop too, not a reverse.
    link.setpoints.send(-0.0, enu(200.0))
    m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
    assert math.copysign(1.0, m.vx) == 1.0


def _records(path: Path) -> list[dict]:
    with gzip.open(path, "rt") as f:
        f.readline()
        return [json.loads(line) for line in f]


def test_our_ardupilot_setpoint_is_what_the_real_firmware_drove_forward_with(edge):
    """shared/sitl/setpoint_semantics: at every recorded heading our setpoint has the very
    fields of the recorder's body-forward one, on which ArduPilot drove forward; the NED
    encoding (the old one) made it reverse exactly where vx <= -FLT_EPSILON."""
    recs = _records(DATA / "sitl" / "setpoint_semantics.jsonl.gz")
    phases = [(i, r) for i, r in enumerate(recs) if r["dir"] == "mark"]
    ap, link, _ = edge(autopilot="ardupilot")
    checked = {"body": 0, "ned": 0}
    for k, (i, mark) in enumerate(phases):
        f = mark["fields"]
        if f.get("encoding") not in ("body", "ned") or f["name"].startswith("reverse"):
            continue
        end = phases[k + 1][0] if k + 1 < len(phases) else len(recs)
        phase = recs[i:end]
        t_end = phase[-1]["t"]
        att = {
            r["fields"]["time_boot_ms"]: r["fields"]["yaw"]
            for r in phase
            if r["type"] == "ATTITUDE" and r["t"] > t_end - 2.0
        }
        signed = [
            (
                g["vx"] * math.cos(att[g["time_boot_ms"]])
                + g["vy"] * math.sin(att[g["time_boot_ms"]])
            )
            / 100
            for g in (r["fields"] for r in phase if r["type"] == "GLOBAL_POSITION_INT")
            if g["time_boot_ms"] in att
        ]
        speed = sum(signed) / len(signed)
        tx = next(
            r["fields"]
            for r in phase
            if r["dir"] == "tx" and r["type"] == "SET_POSITION_TARGET_GLOBAL_INT"
        )
        if f["encoding"] == "body":
            link.setpoints.send(f["speed"], enu(f["yaw_deg"]))
            m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
            assert (m.type_mask, m.coordinate_frame, m.vx, m.vy) == (
                tx["type_mask"],
                tx["coordinate_frame"],
                tx["vx"],
                tx["vy"],
            )
            assert same_angle(m.yaw, tx["yaw"])
            assert speed > 1.4, (mark["fields"]["name"], speed)  # the firmware drove forward
        else:
            reverses = tx["vx"] <= -FLT_EPSILON
            assert (speed < -1.4) if reverses else (speed > 1.4), (f["name"], speed)
        checked[f["encoding"]] += 1
    assert checked == {"body": 8, "ned": 10}  # 8 headings; NED also at 89.99° and 90.01°


def test_px4_setpoints_keep_the_ned_vector_and_stop_along_the_bearing(edge):
    ap, link, _ = edge(autopilot="px4", heading_deg=90.5)
    for compass in COMPASS:
        link.setpoints.send(1.5, enu(compass))
        m = sent_setpoint(ap, "SET_POSITION_TARGET_LOCAL_NED", link)
        assert m.coordinate_frame == 1 and m.type_mask == 2503
        # PX4's rover offboard mode: speed |(vx, vy)|, bearing atan2(vy, vx).
        assert math.hypot(m.vx, m.vy) == pytest.approx(1.5, rel=1e-6)
        assert same_angle(math.atan2(m.vy, m.vx), math.radians(compass), 1e-5), compass
    # The stop: a vanishing vector along the current heading, never (±0, ±0) — the
    # recorded stop_motion at 90.5° (vx = -0.0) swung the rover 48° south.
    for compass in (0.0, 89.5, 90.0, 90.5, 180.0, 270.0):
        ap.heading_deg = compass
        want = enu(compass)
        assert wait_for(
            lambda w=want: same_angle(link.inbox.telemetry.state.heading, w, 2e-4), 1.0, link
        )
        link.setpoints.stop()
        m = sent_setpoint(ap, "SET_POSITION_TARGET_LOCAL_NED", link)
        assert math.hypot(m.vx, m.vy) == pytest.approx(0.001, rel=1e-5)
        assert same_angle(math.atan2(m.vy, m.vx), math.radians(compass), 1e-4), compass
    link.setpoints.send(-1.0, enu(30.0))  # a PX4 rover cannot reverse: a stop along 30°
    m = sent_setpoint(ap, "SET_POSITION_TARGET_LOCAL_NED", link)
    assert math.hypot(m.vx, m.vy) == pytest.approx(0.001, rel=1e-5)
    assert same_angle(math.atan2(m.vy, m.vx), math.radians(30.0), 1e-4)


def test_px4_setpoints_never_resume_after_the_stream_paused(edge):
    """PX4 takes OFFBOARD back by itself when setpoints resume after its offboard-loss
    failsafe (shared/sitl-px4 row 17): after a pause > COM_OF_LOSS_T nothing more goes out."""
    ap, link, _ = edge(autopilot="px4")
    link.modes.prepare_and_arm(timeout_s=5.0)
    assert ap.mode == "OFFBOARD" and ap.armed
    assert link.setpoints.send(1.0, 0.0)
    time.sleep(1.1)
    link.poll()
    ap.clear()
    assert link.setpoints.send(1.0, 0.0) is False
    assert link.setpoints.stop() is False
    assert "paused" in link.setpoints.ended
    time.sleep(0.2)
    link.poll()
    assert ap.messages("SET_POSITION_TARGET_LOCAL_NED") == []


def test_px4_failsafe_mode_change_is_a_failsafe_and_ends_the_stream(edge):
    ap, link, _ = edge(autopilot="px4")
    link.modes.prepare_and_arm(timeout_s=5.0)
    for _ in range(5):
        assert link.setpoints.send(1.0, 0.0)
        link.poll()
        time.sleep(0.05)
    ap.mav.statustext_send(4, b"Failsafe activated\t")  # the recorded PX4 text
    ap.mode = "POSCTL"
    assert wait_for(lambda: link.modes.pilot_took_over, 1.0, link)
    assert link.modes.failsafe_took_over and "POSCTL" in link.modes.takeover_reason
    assert "Failsafe activated" in link.modes.takeover_reason
    assert link.setpoints.ended and link.setpoints.send(1.0, 0.0) is False


def test_ardupilot_mode_lost_after_arming_is_requested_again(edge):
    """The RC mode switch sets MANUAL just after arming, once (shared/sitl row 4)."""
    ap, link, _ = edge(autopilot="ardupilot", mode_after_arm="MANUAL")
    status: list[str] = []
    link.modes.prepare_and_arm(timeout_s=5.0, on_status=status.append)
    assert ap.mode == "GUIDED" and ap.armed and link.watch.mode == "GUIDED"
    assert any(
        "mode changed to MANUAL after arming" in s and "RC mode switch" in s for s in status
    ), status


def test_ardupilot_mode_that_will_not_stay_refuses_to_start_and_disarms(edge):
    ap, link, _ = edge(autopilot="ardupilot", mode_after_arm="MANUAL", mode_switch_repeats=10)
    with pytest.raises(ModeLost) as err:
        link.modes.prepare_and_arm(timeout_s=5.0, on_status=lambda line: None)
    text = str(err.value)
    assert "armed in MANUAL, not GUIDED" in text and "RC mode switch" in text and "disarmed" in text
    assert "\n" not in text
    assert not ap.armed  # never left armed in MANUAL


def test_attitude_alone_does_not_keep_the_telemetry_fresh(edge):
    ap, link, _ = edge(autopilot="ardupilot")
    assert wait_for(lambda: link.link_ok(time.monotonic()), 1.0, link)
    ap.send_position = False  # ATTITUDE still at 20 Hz: the position is frozen
    t_last = link.inbox.telemetry.t_telemetry
    time.sleep(0.8)
    link.poll()
    assert not link.link_ok(time.monotonic())
    assert link.inbox.telemetry.t_telemetry <= t_last + 0.1
    ap.send_position = True
    assert wait_for(lambda: link.link_ok(time.monotonic()), 1.0, link)


def _distance(cm: float, orientation: int = 0, max_cm: int = 2000):
    def send(mav, t):
        mav.distance_sensor_send(
            int(t * 1000), 10, max_cm, int(cm(t)) if callable(cm) else int(cm), 0, 0, orientation, 0
        )

    return send


def test_forward_rangefinder_gives_range_and_range_rate(edge):
    # The PX4 SIH rover's own DISTANCE_SENSOR (recorded, downward: orientation 25) must be ignored.
    with gzip.open(DATA / "sitl-px4" / "stops.jsonl.gz", "rt") as f:
        px4 = next(r["fields"] for r in map(json.loads, f) if r.get("type") == "DISTANCE_SENSOR")
    assert px4["orientation"] == 25
    closing = {"cm": lambda t: 1200 - 50 * t}  # 12 m, closing at 0.5 m/s

    def recorded(mav, t):
        f = dict(px4, time_boot_ms=int(t * 1000))
        mav.distance_sensor_send(**f)

    ap, link, _ = edge(autopilot="ardupilot")
    assert math.isnan(link.inbox.telemetry.range_m)
    ap.extra.append(recorded)
    time.sleep(0.3)
    link.poll()
    assert math.isnan(link.inbox.telemetry.range_m)  # not forward: no ranging
    ap.extra.append(_distance(lambda t: closing["cm"](t)))
    time.sleep(1.0)
    link.poll()
    tel = link.inbox.telemetry
    expected = (1200 - 50 * (time.monotonic() - ap.t0)) / 100
    assert tel.range_m == pytest.approx(expected, abs=0.15)
    assert tel.range_rate_mps == pytest.approx(-0.5, abs=0.05)
    assert time.monotonic() - tel.t_range < 0.2
    closing["cm"] = lambda t: 2000  # at max_distance: nothing in range
    time.sleep(0.3)
    link.poll()
    assert math.isnan(link.inbox.telemetry.range_m) and math.isnan(
        link.inbox.telemetry.range_rate_mps
    )


def test_reconnect_never_blocks_even_when_commands_go_unanswered(edge):
    """A TCP autopilot that answers heartbeats but not commands stalled the old blocking
    reconnect (~1.7 s per attempt inside a tick); ``reconnect(0)`` returns at once."""
    ap, link, lines = edge(transport="tcp", autopilot="ardupilot")
    ap.answer_commands = False
    ap.port.drop_client()  # EOF: a lost link
    assert wait_for(lambda: link.lost, 1.0, link)
    ap.clear()
    longest = 0.0
    end = time.monotonic() + 3.0
    while time.monotonic() < end and not link.link_ok(time.monotonic()):
        t0 = time.monotonic()
        link.reconnect(0.0)
        link.poll()
        longest = max(longest, time.monotonic() - t0)
        time.sleep(0.02)
    assert link.link_ok(time.monotonic()) and not link.lost
    assert longest < 0.1, longest
    # The intervals were asked for again, without waiting for the (missing) answers.
    assert wait_for(lambda: len(ap.messages("COMMAND_LONG")) >= 2, 1.0, link)
    assert any("reopened" in line for line in lines)


def test_serial_link_over_a_pseudo_terminal(edge):
    """The ``/dev/tty*`` path (pyserial) with real MAVLink bytes through a pty pair."""
    ap, link, _ = edge(transport="pty", autopilot="ardupilot", link_kwargs={"baud": 115200})
    assert link.url.startswith("/dev/") and link.autopilot == "ardupilot"
    assert link.telemetry_rates == {"GLOBAL_POSITION_INT": 20.0, "ATTITUDE": 20.0}
    link.modes.prepare_and_arm(timeout_s=5.0)
    assert ap.armed and ap.mode == "GUIDED"
    link.setpoints.send(1.0, enu(200.0))
    m = sent_setpoint(ap, "SET_POSITION_TARGET_GLOBAL_INT", link)
    assert m.vx == 1.0 and m.vy == 0.0 and same_angle(m.yaw, math.radians(200.0), 1e-5)


def test_ardupilot_mode_lost_while_waiting_to_arm_is_set_again_before_arming(edge):
    """shared/sitl boot_and_arm: GUIDED set early in boot is replaced by MANUAL (RC mode
    switch) while arming is still refused; ArduPilot would then arm in MANUAL."""
    ap, link, _ = edge(autopilot="ardupilot", arm_refusals=2, mode_at=(0.9, "MANUAL"))
    status: list[str] = []
    link.modes.prepare_and_arm(timeout_s=8.0, on_status=status.append)
    assert ap.armed and ap.mode == "GUIDED" and link.watch.mode == "GUIDED"
    assert ap.arm_modes[-1] == "GUIDED" and "MANUAL" not in ap.arm_modes[-1:]
    assert any(
        "mode is MANUAL" in s and "requesting GUIDED again before arming" in s for s in status
    ), status
