"""The calibration workflow (docs/calibration.md) on real-firmware convoy runs.

``tests/data/sitl-convoy`` holds the deploy logs of three ArduPilot Rover 4.7 SITL convoy runs
(its README gives their provenance). Each is calibrated end to end as a user would: ``fit-plant
RUN --convoy --out-convoy`` -> ``sim --convoy FITTED`` -> ``compare RUN SIM``, whose verdict
line must say the sim reproduces the run: p95 platooning error within 10 % and string
stability on the same side of 1 (issue 27).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.comms.loss import LossConfig
from openconvoy.convoy import load_convoy
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.experiments import calibration as cal
from openconvoy.logs import read_log
from tests.firmware_runs import PX4_CONVOY as PX4_DATA
from tests.firmware_runs import SITL_CONVOY as DATA
from tests.firmware_runs import unpack as _unpack


def _workflow(
    run: str,
    tmp: Path,
    capsys: pytest.CaptureFixture[str],
    data: Path = DATA,
    seeds: tuple[int, ...] = (0,),
) -> tuple[dict, str]:
    """fit-plant -> sim -> compare on one recorded run: (compare's JSON, its text) of the
    first seed; with more ``seeds`` the JSONs of all under ``"seeds"``."""
    run_dir = _unpack(run, tmp, data)
    fitted = tmp / f"{run}-fitted" / "convoy.toml"
    convoy = str(data / "convoy.toml")
    assert main(["fit-plant", str(run_dir), "--convoy", convoy, "--out-convoy", str(fitted)]) == 0
    results, texts = [], []
    for seed in seeds:
        sim = tmp / f"{run}-sim-{seed}"
        args = ["sim", "--convoy", str(fitted), "--policy", "paper", "--out", str(sim)]
        assert main([*args, "--seed", str(seed), "--quiet", "--no-plots"]) == 0
        capsys.readouterr()
        out_json = tmp / f"{run}-compare-{seed}.json"
        argv = ["compare", str(run_dir), str(sim), "--convoy", convoy, "--out", str(out_json)]
        assert main(argv) == 0
        results.append(json.loads(out_json.read_text()))
        texts.append(capsys.readouterr().out)
    return {**results[0], "seeds": results}, texts[0]


@pytest.mark.e2e
def test_calibration_workflow_end_to_end(tmp_path: Path, capsys) -> None:
    """vx-fixed-1: the fitted files, the sim seeing the run's message ages, and the verdict."""
    result, text = _workflow("vx-fixed-1", tmp_path, capsys)
    fitted = load_convoy(tmp_path / "vx-fixed-1-fitted" / "convoy.toml")
    assert fitted.scenario == "paper" and fitted.vehicles == ("1/10", "1/6", "1/10")
    assert len(fitted.plants) == 3 and all(Path(v).is_file() for v in fitted.plants)
    links = {(int(e[0]), int(e[1])): e[2:] for e in fitted.channel.link_latency_s}
    # Follower 1 used the leader's messages at 32-45 ms, follower 2 follower 1's at 51-63:
    # 23 and 43 ms after they left, the senders' telemetry 10 ms old (stamped, not delayed).
    assert 0.021 < float(np.median(links[(0, 1)])) < 0.026
    assert 0.040 < float(np.median(links[(1, 2)])) < 0.045
    assert fitted.channel.staleness_s == pytest.approx((0.01, 0.01, 0.035), abs=0.003)
    assert fitted.channel.per == 0.0 and fitted.channel.stamp_error_s == 0.0
    # The sim's follower 1 first uses each message as old as on the firmware.
    sim_log = read_log(tmp_path / "vx-fixed-1-sim-0")
    ages = cal.message_ages_at_first_use(sim_log, 1)
    assert abs(float(np.median(ages)) - 0.0338) < 0.004
    # The verdict, on the leader's 60 s drive.
    assert "A window: the leader's drive, 60.0 s from its start" in text
    (line,) = [x for x in text.splitlines() if x.startswith("verdict:")]
    assert line.startswith("verdict: MATCH: B/A p95 ")
    r = result["verdict"]["ratios"]
    assert abs(r["p95_platooning_error_m"] - 1.0) <= 0.10
    assert f"{r['p95_platooning_error_m']:.3f}" in line
    assert abs(r["mean_speed_difference_mps"] - 1.0) < 0.15


ARDUPILOT_RUNS = {"vx-fixed-1": 0.315, "vx-fixed-2": 0.303, "vx-fixed-per0.3": 0.538}
"""Every nominal ArduPilot run recorded, and its firmware p95 (m) on the leader's drive."""


@pytest.mark.e2e
@pytest.mark.parametrize("run", sorted(ARDUPILOT_RUNS))
def test_fitted_sim_reproduces_every_ardupilot_run(run: str, tmp_path: Path, capsys) -> None:
    """Issue 27's must-show on every nominal ArduPilot run: the fitted sim's p95 within 10 %
    of the firmware's and string stability on the same side of 1, on two sim seeds. It
    holds because the channel is fitted as the vehicles' was: each message delivered after
    the phase between the loops and stamped older by its sender's telemetry staleness
    (which the plant's loop delay already holds), and a lossy run's drops replayed
    (vx-fixed-per0.3; drawn at its PER instead, one run is one draw: 0.97-1.34)."""
    result, _ = _workflow(run, tmp_path, capsys, seeds=(0, 1))
    fitted = load_convoy(tmp_path / f"{run}-fitted" / "convoy.toml")
    for r in result["seeds"]:
        assert r["metrics"]["p95_platooning_error_m"]["a"] == pytest.approx(
            ARDUPILOT_RUNS[run], abs=0.001
        )
        v = r["verdict"]
        assert abs(v["ratios"]["p95_platooning_error_m"] - 1.0) <= 0.10, v
        assert v["string_same_side"], v
    if run == "vx-fixed-per0.3":
        links = {(int(e[0]), int(e[1])): e[2:] for e in fitted.channel.lost_s}
        # 30 % of ~620 broadcasts on each link the followers use, none on the PER 0 runs.
        assert set(links) == {(0, 1), (1, 2), (0, 2), (2, 1)}
        assert all(150 < len(v) < 215 for v in links.values()), {
            k: len(v) for k, v in links.items()
        }
    else:
        assert fitted.channel.lost_s == ()


@pytest.mark.e2e
def test_fitted_sim_reproduces_the_px4_firmware_run(tmp_path: Path, capsys) -> None:
    """sitl-px4/convoy r2: the fitted sim within 20 % of the firmware's p95 (issue 27), its
    string stability on the same side of 1. What makes it: the autopilot clock running
    slow (SIH 0.990) stamps every message 0.1-0.6 s old, so members place their
    predecessors too far on and, past the fresh age, as if braking at the deployed
    presets' limit (the fitted channel's stamp error, the convoy's declared vehicles)."""
    result, _ = _workflow("r2", tmp_path, capsys, data=PX4_DATA)
    fitted = load_convoy(tmp_path / "r2-fitted" / "convoy.toml")
    ch = fitted.channel
    # Follower 1's clock 30 ms behind at the start, the leader's 55 ms (25 more, stamped
    # with its staleness, 0 for the leader); both fall behind 9.3 ms/s.
    assert 0.020 < ch.stamp_error_s < 0.040 and 0.015 < ch.staleness_s[0] < 0.035
    assert 0.007 < ch.stamp_drift < 0.011  # SIH's 0.990 less the bridge's creep
    v = result["verdict"]
    assert result["metrics"]["p95_platooning_error_m"]["a"] == pytest.approx(2.671, abs=0.001)
    assert abs(v["ratios"]["p95_platooning_error_m"] - 1.0) <= 0.20, v
    assert v["string_same_side"], v


PX4_DEMO_S = 60.0
"""The PX4 demo's length in its calibration test (s): the paper scenario's whole drive."""


@pytest.mark.e2e
@pytest.mark.netns
def test_the_calibration_loop_closes_on_the_simulated_px4_vehicles(tmp_path: Path, capsys) -> None:
    """Issue 27: the simulated PX4 vehicles driven by ``deploy`` (``demo --autopilot px4``:
    real MAVLink over UDP, signed BSMs over multicast in a private namespace), calibrated
    from that run's logs (``fit-plant``, vehicles and channel), simulated (``sim``) and
    compared (``compare``): the p95 platooning error within 10 % and string stability on
    the same side of 1. Each vehicle's logged speed is its track speed times the cosine of
    its fitted heading bias (``bridge/simvehicle``'s PX4 drives its true velocity, the
    deploy projects it on the believed heading), as the fitted plant models it."""
    import subprocess
    import sys

    from openconvoy.comms.netns import netns_unavailable_reason

    reason = netns_unavailable_reason()
    assert reason is None, f"the demo needs a private network namespace: {reason}"
    demo_dir = tmp_path / "demo"
    argv = [sys.executable, "-m", "openconvoy.cli", "demo", "--autopilot", "px4"]
    argv += ["--duration", repr(PX4_DEMO_S), "--out", str(demo_dir)]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    run, convoy = demo_dir / "deploy", demo_dir / "convoy.toml"
    fitted = tmp_path / "fitted" / "convoy.toml"
    assert main(["fit-plant", str(run), "--convoy", str(convoy), "--out-convoy", str(fitted)]) == 0
    log = read_log(run)
    for vid in range(3):
        bias = vehicle_preset(load_convoy(fitted).plants[vid]).heading_bias_rad
        assert abs(cal.speed_scale(log, vid) - math.cos(bias)) < 0.003, (vid, bias)
    sim = tmp_path / "sim"
    args = ["sim", "--convoy", str(fitted), "--policy", "paper", "--out", str(sim), "--seed", "0"]
    assert main([*args, "--duration", repr(PX4_DEMO_S), "--quiet", "--no-plots"]) == 0
    capsys.readouterr()
    out_json = tmp_path / "compare.json"
    assert (
        main(["compare", str(run), str(sim), "--convoy", str(convoy), "--out", str(out_json)]) == 0
    )
    v = json.loads(out_json.read_text())["verdict"]
    assert abs(v["ratios"]["p95_platooning_error_m"] - 1.0) <= 0.10, v
    assert v["string_same_side"], v


def _log(t: np.ndarray, vid: int, ages: np.ndarray, tel: np.ndarray | None = None) -> dict:
    n = len(t)
    out = {
        "t_s": t,
        "vehicle_id": np.full(n, vid),
        "pred_msg_age_s": ages,
        "msgs_received": np.arange(n),
        "msgs_lost": np.zeros(n, dtype=int),
    }
    if tel is not None:
        out["telemetry_age_s"] = tel
    return out


def _merge(*logs: dict) -> dict:
    return {k: np.concatenate([lg[k] for lg in logs]) for k in logs[0]}


def test_first_use_ages_are_where_the_age_falls() -> None:
    t = np.arange(8) * 0.05
    ages = np.array([0.034, 0.084, 0.034, 0.084, 0.134, 0.032, 0.082, 0.031])
    got = cal.message_ages_at_first_use(_log(t, 1, ages), 1)
    assert got.tolist() == [0.034, 0.034, 0.032, 0.031]


def test_link_delays_compose_phases_along_the_string() -> None:
    """0 -> 1 delivered 24 ms after its send, 1 -> 2 43 ms (vx-fixed-1's phases): 0 -> 2's
    phase is 67 mod 50 = 17 ms."""
    delays = {1: np.full(50, 0.024), 2: np.full(50, 0.043)}
    links = cal.link_delays(delays, 0.05, 5)
    by = {(int(e[0]), int(e[1])): e[2:] for e in links}
    assert by[(0, 1)] == (0.024,) * 5 and by[(1, 2)] == (0.043,) * 5
    assert by[(0, 2)] == (pytest.approx(0.017),)
    LossConfig(link_latency_s=links)  # what the channel accepts


def test_delivery_delays_match_the_stamp_to_the_senders_tick() -> None:
    """A message first used at t with age a carries stamp t - a: the sender's first row with
    that stamp (row time less its telemetry age) sent it, so its delay is t less that row's
    time, however old the telemetry was (vx-fixed-2: ages 8 or 46 ms, delays 7 ms)."""
    t = np.arange(0.0, 2.0, 0.05)
    tel = np.where(np.arange(len(t)) % 4 == 0, 0.001, 0.039)  # the sender's staleness
    lead = _log(t, 0, np.full(len(t), np.nan), tel)
    # Each broadcast first used 7 ms after it left, on the receiver's next tick.
    follower = _log(t + 0.007, 1, tel + 0.007, np.full(len(t), 0.01))
    log = _merge(lead, follower)
    a = cal.message_ages_at_first_use(log, 1)
    assert sorted(set(np.round(a, 3))) == [0.008, 0.046]
    d = cal.delivery_delays(log, 1, np.full(len(a), -1.0))
    assert np.allclose(d, 0.007)
    # Without telemetry ages the fallback stands.
    bare = {k: v for k, v in log.items() if k != "telemetry_age_s"}
    assert (cal.delivery_delays(bare, 1, np.full(len(a), -1.0)) == -1.0).all()
    fit = cal.fit_channel(log, {0: 0.03, 1: 0.01})
    assert fit.staleness_s == (0.03, 0.01)
    assert fit.link_latency_s[0][2:] == pytest.approx((0.007,) * cal.QUANTILES)


def _lossy_vehicle(
    vid: int,
    phase: float,
    sender_times: np.ndarray,
    heard: dict[float, bool],
    lost: list,
    signed: bool = False,
) -> dict:
    """A vehicle's rows every 50 ms from ``phase`` (s): broadcasting on odd rows (telemetry
    10 ms old), using the newest of its predecessor's broadcasts that ``heard`` says
    arrived (``sender_times``: their send times), counting the drops in ``lost``
    (send time + arrival delay) on the row after each. Messages carry the telemetry
    sample's time, or with ``signed`` their send time (D50)."""
    t = np.arange(60) * 0.05 + phase
    sent = (np.arange(60) + 1) // 2
    ages = np.full(len(t), np.nan)
    got = [s for s in sender_times if heard.get(round(float(s), 3), True)]
    for k, now in enumerate(t):
        before = [s for s in got if s < now]
        if vid > 0 and before:
            ages[k] = now - (before[-1] - (0.0 if signed else 0.01))
    drops = np.array([np.sum(np.asarray(lost) < now) for now in t])
    return {
        "t_s": t,
        "vehicle_id": np.full(len(t), vid),
        "pred_msg_age_s": ages,
        "msgs_received": np.arange(len(t)),
        "msgs_lost": drops,
        "msgs_sent": sent,
        "telemetry_age_s": np.full(len(t), 0.01),
    }


def test_recorded_losses_per_link_and_the_leaders_to_the_last_follower() -> None:
    """Three vehicles, broadcasts at 10 Hz: 0 -> 1 dropped two, 1 -> 2 one, 0 -> 2 two. The
    predecessors' drops are the broadcasts whose stamp was never used; the leader's to
    follower 2 are what is left of its drop counter, each given to the leader's latest
    broadcast due by then."""
    b0 = np.round(np.arange(1, 60, 2) * 0.05, 3)
    b1 = np.round(b0 + 0.007, 3)
    lost01, lost12, lost02 = [b0[3], b0[7]], [b1[5]], [b0[10], b0[11]]
    lead = _lossy_vehicle(0, 0.0, b0, {}, [])
    f1 = _lossy_vehicle(1, 0.007, b0, {x: x not in lost01 for x in b0}, [x + 0.001 for x in lost01])
    f2 = _lossy_vehicle(
        2, 0.02, b1, {x: x not in lost12 for x in b1},
        [x + 0.001 for x in lost12] + [x + 0.015 for x in lost02],
    )  # fmt: skip
    log = _merge(lead, f1, f2)
    got01, window = cal.recorded_losses(log, 1)
    assert got01.tolist() == pytest.approx(lost01) and window == pytest.approx(0.05)
    got12, _ = cal.recorded_losses(log, 2)
    assert got12.tolist() == pytest.approx(lost12)
    got02 = cal.other_sender_losses(log, 2, 0, got12, 0.013, 0.02)
    assert got02.tolist() == pytest.approx(lost02)
    fit = cal.fit_channel(log, 0.01)
    assert fit.per > 0.0 and fit.lost_window_s == pytest.approx(0.05)
    by = {(int(e[0]), int(e[1])): list(e[2:]) for e in fit.lost_s}
    assert by[(0, 1)] == pytest.approx(lost01) and by[(1, 2)] == pytest.approx(lost12)
    assert by[(0, 2)] == pytest.approx(lost02)
    # A log without telemetry ages cannot tell: nothing replayed.
    assert cal.recorded_losses({k: v for k, v in log.items() if k != "telemetry_age_s"}, 1) is None


def test_signed_messages_carry_their_send_time_and_no_staleness() -> None:
    """A signed run (D50): the first uses match the senders' row times, not their telemetry
    stamps, so the ages are the delays and nothing is stamped (the demo: 40 / 21 ms)."""
    b0 = np.round(np.arange(1, 60, 2) * 0.05, 3)
    b1 = np.round(b0 + 0.007, 3)
    logs = [
        _lossy_vehicle(0, 0.0, b0, {}, [], signed=True),
        _lossy_vehicle(1, 0.007, b0, {}, [], signed=True),
        _lossy_vehicle(2, 0.02, b1, {}, [], signed=True),
    ]
    log = _merge(*logs)
    assert cal.stamp_source(log, 1) == "send" and cal.stamp_source(log, 2) == "send"
    fit = cal.fit_channel(log, 0.01)
    assert fit.staleness_s == (0.0, 0.0, 0.0) and fit.stamp_error_s == 0.0
    by = {(int(e[0]), int(e[1])): e[2:] for e in fit.link_latency_s}
    assert float(np.median(by[(0, 1)])) == pytest.approx(0.007)
    assert float(np.median(by[(1, 2)])) == pytest.approx(0.013)
    unsigned = _merge(
        *[_lossy_vehicle(v, p, b, {}, []) for v, p, b in ((0, 0, b0), (1, 0.007, b0))]
    )
    assert cal.stamp_source(unsigned, 1) == "telemetry"


def test_heading_bias_is_the_logged_heading_less_the_track() -> None:
    """A vehicle driving 10 degrees north of east while logging a heading of 2 degrees:
    its bias is -8 degrees; one at rest has none."""
    t = np.arange(100) * 0.05
    track = math.radians(10.0)
    log = {
        "t_s": t,
        "vehicle_id": np.zeros(100, dtype=int),
        "x_m": t * math.cos(track),
        "y_m": t * math.sin(track),
        "heading_rad": np.full(100, math.radians(2.0)),
    }
    assert math.degrees(cal.heading_bias(log, 0)) == pytest.approx(-8.0)
    log["x_m"], log["y_m"] = np.zeros(100), np.zeros(100)
    assert cal.heading_bias(log, 0) == 0.0


def test_speed_scale_is_the_logged_speed_over_the_track() -> None:
    """A vehicle moving 1.2 m/s along its track that logs 0.986 of it (the PX4 demo's
    follower 1, cos(-9.6 degrees)): its scale is 0.986; a step in the logged speed (a span
    where the two part by 0.3 m/s) and rows at rest are left out; too little motion: 1."""
    t = np.arange(400) * 0.05
    log = {
        "t_s": t,
        "vehicle_id": np.zeros(400, dtype=int),
        "x_m": 1.2 * t,
        "y_m": np.zeros(400),
        "speed_mps": np.full(400, 0.986 * 1.2),
    }
    log["speed_mps"][200:205] = 3.0  # an outlier stretch
    assert cal.speed_scale(log, 0) == pytest.approx(0.986, abs=1e-3)
    log["x_m"] = np.zeros(400)
    assert cal.speed_scale(log, 0) == 1.0


def test_a_clock_error_is_taken_out_of_the_ages_and_stamps_the_messages() -> None:
    """Clocks falling behind 4 ms/s from 0.157 s (vx-fixed-per0.3's telemetry ages, states
    fresh: staleness 0.01 s): the delays are the ages less the sender's error, and the
    channel stamps messages with that error (members dead-reckon to the system clock)."""
    t = np.arange(0.0, 60.0, 0.05)
    err = 0.157 + 0.004 * t
    ages = np.where(np.arange(len(t)) % 2 == 0, 0.03, 0.08) + err
    logs = [_log(t, v, ages if v else np.full(len(t), np.nan), err + 0.01) for v in (0, 1, 2)]
    fit = cal.fit_channel(_merge(*logs), 0.01)
    assert fit.stamp_error_s == pytest.approx(0.157, abs=0.003)
    assert fit.stamp_drift == pytest.approx(0.004, abs=1e-4)
    assert float(np.median(fit.ages_s[1])) == pytest.approx(0.03, abs=0.002)
    assert fit.per == 0.0
    # Clocks that keep time: ages are delays, no stamp error.
    logs = [
        _log(t, v, ages - err if v else np.full(len(t), np.nan), t * 0 + 0.01) for v in (0, 1, 2)
    ]
    fit = cal.fit_channel(_merge(*logs), 0.01)
    assert fit.stamp_error_s == 0.0 and fit.stamp_drift == 0.0


def test_verdict_ratios_and_sides() -> None:
    a = {"p95_platooning_error_m": 0.3, "string_stability": 1.3, "mean_speed_difference_mps": 0.1}
    b = {"p95_platooning_error_m": 0.32, "string_stability": 1.1, "mean_speed_difference_mps": 0.2}
    v = cal.verdict(a, b)
    assert v["match"] and v["ratios"]["p95_platooning_error_m"] == pytest.approx(0.32 / 0.3)
    assert cal.format_verdict(v) == (
        "verdict: MATCH: B/A p95 1.067 (within 10 %), string stability 0.846 "
        "(same side of 1), speed difference 2.000"
    )
    b["string_stability"] = 0.9
    assert not cal.verdict(a, b)["match"]
    b.update(string_stability=1.2, p95_platooning_error_m=0.4)
    assert not cal.verdict(a, b)["p95_within"]
    assert math.isnan(cal.ratios({"p95_platooning_error_m": 0.0}, b)["p95_platooning_error_m"])


def test_calibration_refuses_what_it_cannot_fit(tmp_path: Path) -> None:
    with pytest.raises(Exception, match="not a run directory"):
        cal.calibrate(tmp_path / "missing", DATA / "convoy.toml", tmp_path / "out.toml")
    assert main(["fit-plant", str(tmp_path), "--convoy", str(DATA / "convoy.toml")]) == 2


def _sim_args(convoy: Path, *flags: str):
    from openconvoy.cli import build_parser

    return build_parser().parse_args(["sim", "--convoy", str(convoy), *flags])


def test_the_convoy_files_channel_feeds_sim_and_flags_override_it(tmp_path: Path) -> None:
    from openconvoy.experiments.commands import run_config_from_args

    (tmp_path / "car.toml").write_text(
        '[vehicle]\nname = "car"\nlength_m = 0.8\nwidth_m = 0.3\nwheelbase_m = 0.33\n'
    )
    convoy = tmp_path / "c.toml"
    convoy.write_text(
        '[convoy]\nvehicles = ["car.toml", "1/10"]\n'
        'plants = ["car.toml", "1/6"]\n'
        "[channel]\nper = 0.2\nlatency_samples_s = [0.03, 0.01]\n"
        "link_latency_s = [[0, 1, 0.034, 0.036]]\nstamp_error_s = 0.05\n"
    )
    loss = run_config_from_args(_sim_args(convoy)).loss.at(0.2)
    assert run_config_from_args(_sim_args(convoy)).per == 0.2
    assert loss.latency_samples_s == (0.01, 0.03) and loss.stamp_error_s == 0.05
    assert loss.link_latency(0, 1).samples_s == (0.034, 0.036)
    # A preset file named relative to the convoy file.
    assert Path(load_convoy(convoy).vehicles[0]) == tmp_path / "car.toml"
    plants = run_config_from_args(_sim_args(convoy)).convoy.plants
    assert Path(plants[0]) == tmp_path / "car.toml" and plants[1] == "1/6"
    over = run_config_from_args(_sim_args(convoy, "--per", "0.1", "--jitter", "0.02"))
    assert over.per == 0.1 and over.loss.jitter_s == 0.02
    assert over.loss.latency_samples_s == () and over.loss.link_latency_s == ()
    convoy.write_text('[convoy]\nvehicles = ["1/10", "1/10"]\nplants = ["1/10"]\n')
    assert main(["sim", "--convoy", str(convoy), "--out", str(tmp_path / "x")]) == 2
    convoy.write_text('[convoy]\nvehicles = ["1/10", "1/10"]\n[channel]\nlatency = 0.1\n')
    assert main(["sim", "--convoy", str(convoy), "--out", str(tmp_path / "x")]) == 2
