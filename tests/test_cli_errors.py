"""Every bad input of shared/findings/input-defects.md (issue 10 item 7, issue 11 item 6):
one line ``openconvoy: error: ...`` naming the flag, key or file and what is allowed, exit
status 2, no traceback, nothing written, nothing moved.

Each probe runs in-process through ``main(argv)``. ``{d}`` in an argument is the probe's
directory, holding the files the probe writes first. Deploy probes point at a MAVLink port
nobody listens on: a value that slipped through validation would end in a connection
timeout (exit 1), not in the one line asserted here.
"""

from __future__ import annotations

import importlib.util
import json
import socket
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.logs import COLUMNS
from openconvoy.policies.learned import META_MEMBER, LearnedMeta, NumpyMLP, save_npz
from openconvoy.policies.presets import PRESETS
from openconvoy.testing import free_port

CONVOY = '[convoy]\nname = "lab"\nvehicles = ["1/10", "1/6"]\n'
DEPLOY = [
    "deploy",
    "--policy",
    "paper",
    "--vehicle-id",
    "1",
    "--convoy",
    "{d}/c.toml",
    "--mavlink",
    "udpout:127.0.0.1:9",
    "--iface",
    "lo",
    "--connect-timeout",
    "1",
]
SIM = ["sim", "--out", "{d}/out", "--quiet", "--no-plots"]
SWEEP = ["experiment", "per-sweep", "--config", "{d}/e.toml", "--out", "{d}/out"]
PRESET = "[vehicle]\nlength_m = 0.8\nwidth_m = 0.3\nwheelbase_m = 0.33\n"
# without the train extra a .zip policy is refused for that reason (one line, naming it)
SB3_LOADS = (
    "SB3 could not load the model"
    if importlib.util.find_spec("stable_baselines3")
    else "train extra"
)
EXPERIMENT = '[experiment]\npolicies = ["paper"]\npers = [0.0]\nseeds = 1\nduration_s = 5.0\n'


def _track(**over: object) -> str:
    c = {"lat": 28.6024, "lon": -81.2001}
    track = {
        "name": "t",
        "center": c,
        "turns": [],
        "straights": [{"start": c, "end": {"lat": 28.6025, "lon": -81.2001}, "speed": 1.0}],
    }
    for key, value in over.items():
        if key in ("speed", "end"):
            track["straights"][0][key] = value
        else:
            track[key] = value
    return json.dumps(track)


def _log(rows: list[dict[str, object]]) -> str:
    lines = [",".join(COLUMNS)]
    for r in rows:
        base = {c: "0" for c in COLUMNS}
        base["mode"] = "coop"
        base.update({k: str(v) for k, v in r.items()})
        lines.append(",".join(base[c] for c in COLUMNS))
    return "\n".join(lines) + "\n"


GOOD_ROWS = [{"t_s": 0.0, "vehicle_id": 0}, {"t_s": 0.0, "vehicle_id": 1, "x_m": -15}]


def _meta() -> LearnedMeta:
    member = PRESETS["paper"].member
    return LearnedMeta(
        algo="ppo",
        layout=member.layout.describe(),
        member_config=member,
        control_rate_hz=20.0,
        action_low=(0.0, -0.5),
        action_high=(5.0, 0.5),
    )


def _npz(path: Path, nan: bool = False) -> None:
    size = _meta().layout["size"]
    mlp = NumpyMLP([np.ones((2, size))], [np.zeros(2)], "tanh", "clip")
    save_npz(path, _meta(), mlp)
    if nan:  # rewrite one weight as NaN, as a diverged training run would leave it
        with np.load(path, allow_pickle=False) as data:
            arrays = dict(data)
        arrays["W0"] = np.full_like(arrays["W0"], np.nan)
        with open(path, "wb") as f:
            np.savez(f, **arrays)


def _zip(path: Path, meta_json: str | None = None) -> None:
    import zipfile

    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(
            META_MEMBER, meta_json if meta_json is not None else json.dumps(_meta().to_json())
        )
        zf.writestr("policy.pth", b"\x00 not torch weights")
        zf.writestr("data", "{not json")


# (id, files {name: text | bytes | callable(path)}, argv, words the line must contain)
PROBES: list[tuple[str, dict, list[str], str]] = [
    # D5: [safety] NaN / inf / negative / string
    (
        "D5-cap-nan",
        {"c.toml": CONVOY + "[safety]\nspeed_cap_mps = nan\n"},
        DEPLOY,
        "safety.speed_cap_mps: nan",
    ),
    (
        "D5-fence-nan",
        {"c.toml": CONVOY + "[safety]\ngeofence_radius_m = nan\n"},
        DEPLOY,
        "safety.geofence_radius_m",
    ),
    ("D5-gap-nan", {"c.toml": CONVOY + "[safety]\nmin_gap_m = nan\n"}, DEPLOY, "safety.min_gap_m"),
    (
        "D5-fence-inf",
        {"c.toml": CONVOY + "[safety]\ngeofence_radius_m = inf\n"},
        DEPLOY,
        "(0, 100000]",
    ),
    (
        "D5-gap-negative",
        {"c.toml": CONVOY + "[safety]\nmin_gap_m = -1.0\n"},
        DEPLOY,
        "safety.min_gap_m: -1.0",
    ),
    (
        "D5-age-string",
        {"c.toml": CONVOY + '[safety]\nmax_msg_age_s = "5"\n'},
        DEPLOY,
        "expected a number, got the string '5'",
    ),
    # D6: deploy --rate and --log checked before connecting
    ("D6-rate-nan", {"c.toml": CONVOY}, [*DEPLOY, "--rate", "nan"], "--rate: nan is out of range"),
    (
        "D6-rate-1e6",
        {"c.toml": CONVOY},
        [*DEPLOY, "--rate", "1e6"],
        "--rate: 1e6 is out of range; allowed: a finite number in [5, 100]",
    ),
    ("D6-rate-inf", {"c.toml": CONVOY}, [*DEPLOY, "--rate", "inf"], "--rate"),
    (
        "D6-log-file",
        {"c.toml": CONVOY + '[v2v]\nauth = "off"\n', "f.txt": "x"},
        [*DEPLOY, "--log", "{d}/f.txt"],
        "--log",
    ),
    # D8, D9, D45: deploy's other numbers
    (
        "D8-per-negative",
        {"c.toml": CONVOY},
        [*DEPLOY, "--per", "-1"],
        "--per: -1 is out of range; allowed: a finite number in [0, 1]",
    ),
    ("D8-per-nan", {"c.toml": CONVOY}, [*DEPLOY, "--per", "nan"], "--per"),
    (
        "D9-connect-timeout-nan",
        {"c.toml": CONVOY},
        [*DEPLOY, "--connect-timeout", "nan"],
        "--connect-timeout",
    ),
    ("D45-duration-negative", {"c.toml": CONVOY}, [*DEPLOY, "--duration", "-5"], "--duration"),
    (
        "D45-arm-timeout-negative",
        {"c.toml": CONVOY},
        [*DEPLOY, "--arm-timeout", "-1"],
        "--arm-timeout",
    ),
    # D10, D14: file-system refusals name the file; outputs that are directories
    (
        "D10-convoy-is-a-dir",
        {"c.toml/x": "x"},
        [*SIM, "--convoy", "{d}/c.toml"],
        "c.toml: is a directory",
    ),
    (
        "D14-report-out-dir",
        {"log.csv": _log(GOOD_ROWS), "m/x": "x"},
        ["report", "{d}/log.csv", "--out", "{d}/m"],
        "--out",
    ),
    (
        "D14-compare-out-dir",
        {"a.csv": _log(GOOD_ROWS), "m/x": "x"},
        ["compare", "{d}/a.csv", "{d}/a.csv", "--out", "{d}/m"],
        "--out",
    ),
    (
        "D14-fit-plant-out-dir",
        {"log.csv": _log(GOOD_ROWS), "m/x": "x"},
        ["fit-plant", "{d}/log.csv", "--out", "{d}/m"],
        "--out",
    ),
    # D13, D25, D26, D38: sim flags
    ("D13-duration-inf", {}, [*SIM, "--duration", "inf"], "--duration: inf is out of range"),
    ("D25-duration-nan", {}, [*SIM, "--duration", "nan"], "--duration"),
    (
        "D26-seed-negative",
        {},
        [*SIM, "--seed", "-5"],
        "--seed: -5 is out of range; allowed: an integer",
    ),
    ("D38-latency-nan", {}, [*SIM, "--latency", "nan"], "--latency"),
    ("D38-latency-negative", {}, [*SIM, "--latency", "-1"], "--latency"),
    ("D38-jitter-negative", {}, [*SIM, "--jitter", "-1"], "--jitter"),
    ("D38-gps-noise-nan", {}, [*SIM, "--gps-noise", "nan"], "--gps-noise"),
    ("D38-ranging-range-negative", {}, [*SIM, "--ranging-range", "-5"], "--ranging-range"),
    # D15, D16, D29, D39: convoy types
    (
        "D15-vehicles-ints",
        {"c.toml": "[convoy]\nvehicles = [1, 2]\n"},
        [*SIM, "--convoy", "{d}/c.toml"],
        "vehicles[0]: expected a string, got int 1",
    ),
    (
        "D15-convoy-not-a-table",
        {"c.toml": "convoy = 5\n"},
        [*SIM, "--convoy", "{d}/c.toml"],
        "convoy must be a table",
    ),
    (
        "D16-hop-limit-string",
        {"c.toml": CONVOY + '[v2v]\nhop_limit = "x"\n'},
        DEPLOY,
        "v2v.hop_limit: expected an integer",
    ),
    (
        "D29-vehicles-string",
        {"c.toml": '[convoy]\nvehicles = "1/10"\n'},
        [*SIM, "--convoy", "{d}/c.toml"],
        "vehicles: expected a list of strings",
    ),
    (
        "D29-origin-string",
        {"c.toml": '[convoy]\norigin = "here"\n'},
        [*SIM, "--convoy", "{d}/c.toml"],
        "origin: expected a list of 3 numbers",
    ),
    (
        "D39-name-int",
        {"c.toml": "[convoy]\nname = 5\n"},
        [*SIM, "--convoy", "{d}/c.toml"],
        "name: expected a string",
    ),
    # D17, D25, D40: policy files
    (
        "D17-kp-string",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.speed]\nkp = "high"\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "policy.speed.kp: expected a number",
    ),
    (
        "D17-kp-nan",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.speed]\nkp = nan\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "policy.speed.kp: nan",
    ),
    (
        "D17-member-int",
        {"p.toml": '[policy]\nbase = "paper"\nmember = 5\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "policy.member: expected a table",
    ),
    (
        "D25-control-rate-nan",
        {"p.toml": '[policy]\nbase = "paper"\ncontrol_rate_hz = nan\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "control_rate_hz",
    ),
    (
        "D40-kd-negative",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.speed]\nkd = -100\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "kd: -100",
    ),
    (
        "D40-k-huge",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.member]\nk = 100000\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "member.k: 100000",
    ),
    (
        "D40-speed-limit-inf",
        {"p.toml": '[policy]\nbase = "paper"\nspeed_limit_mps = inf\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "speed_limit_mps",
    ),
    (
        "D40-distance-negative",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.member.spacing]\ndistance_m = -15\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "spacing.distance_m",
    ),
    (
        "D40-enabled-string",
        {"p.toml": '[policy]\nbase = "paper"\n[policy.member.ladder]\nenabled = "yes"\n'},
        [*SIM, "--policy", "{d}/p.toml"],
        "ladder.enabled: expected true or false",
    ),
    # D18, D31, D41: vehicle presets
    (
        "D18-length-string",
        {"v.toml": PRESET.replace("0.8", '"long"')},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "vehicle.length_m: expected a number",
    ),
    (
        "D18-no-wheelbase",
        {"v.toml": "[vehicle]\nlength_m = 0.8\nwidth_m = 0.3\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "missing key(s) wheelbase_m",
    ),
    (
        "D18-delay-1e9",
        {"v.toml": PRESET + "actuation_delay_s = 1e9\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "actuation_delay_s",
    ),
    (
        "D31-malformed",
        {"v.toml": "[vehicle\nlength_m = 1\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "v.toml: invalid TOML",
    ),
    (
        "D41-negative-length",
        {"v.toml": PRESET.replace("0.8", "-0.8")},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "vehicle.length_m: -0.8",
    ),
    (
        "D41-zero-accel",
        {"v.toml": PRESET + "accel_max_mps2 = 0.0\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "accel_max_mps2",
    ),
    (
        "D41-nan-decel",
        {"v.toml": PRESET + "decel_max_mps2 = nan\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "decel_max_mps2",
    ),
    (
        "D41-negative-lag",
        {"v.toml": PRESET + "speed_lag_s = -1.0\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "speed_lag_s",
    ),
    (
        "D41-zero-wheelbase",
        {"v.toml": PRESET.replace("0.33", "0.0")},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "wheelbase_m",
    ),
    (
        "D41-inf-speed",
        {"v.toml": PRESET + "max_speed_mps = inf\n"},
        [*SIM, "--vehicle-preset", "{d}/v.toml"],
        "max_speed_mps",
    ),
    # D19, D25, D28, D42: track files
    (
        "D19-lat-null",
        {"t.json": _track(center={"lat": None, "lon": 0.0})},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "center.lat: expected a number",
    ),
    (
        "D19-deploy-track-lat-null",
        {"c.toml": CONVOY, "t.json": _track(center={"lat": None, "lon": 0.0})},
        [*DEPLOY[:4], "0", *DEPLOY[5:], "--track", "{d}/t.json"],
        "center.lat",
    ),
    ("D19-empty-track-path", {}, [*SIM, "--scenario", "track-file:"], "'track-file:' needs a path"),
    (
        "D25-track-lat-nan",
        {"t.json": _track(center={"lat": float("nan"), "lon": 0.0})},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "center.lat: nan",
    ),
    (
        "D28-track-lat-abc",
        {"t.json": _track(center={"lat": "abc", "lon": 0.0})},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "t.json: center.lat: expected a number, got 'abc'",
    ),
    (
        "D42-lat-999",
        {"t.json": _track(end={"lat": 999.0, "lon": 0.0})},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "straights[0].end.lat: 999.0 is out of range",
    ),
    (
        "D42-18000-km",
        {"t.json": _track(end={"lat": -28.0, "lon": 98.0})},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "km from the track's center",
    ),
    (
        "D42-negative-speed",
        {"t.json": _track(speed=-1.0)},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "straights[0].speed: -1.0",
    ),
    (
        "D42-zero-speed",
        {"t.json": _track(speed=0)},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "speed",
    ),
    (
        "D42-huge-speed",
        {"t.json": _track(speed=1e6)},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "speed",
    ),
    (
        "D42-closed-loop-string",
        {"t.json": _track(closed_loop="no")},
        [*SIM, "--scenario", "track-file:{d}/t.json"],
        "closed_loop: expected true or false",
    ),
    # D13, D29, D38, D44: experiment files and --pers
    (
        "D13-experiment-duration-inf",
        {"e.toml": EXPERIMENT.replace("5.0", "inf")},
        SWEEP,
        "duration_s: inf",
    ),
    (
        "D29-pers-string",
        {"e.toml": EXPERIMENT.replace("[0.0]", '"0.1"')},
        SWEEP,
        "pers: expected a list of numbers",
    ),
    (
        "D29-policies-string",
        {"e.toml": EXPERIMENT.replace('["paper"]', '"paper"')},
        SWEEP,
        "policies: expected a list of strings",
    ),
    (
        "D29-seeds-fraction",
        {"e.toml": EXPERIMENT.replace("seeds = 1", "seeds = 2.5")},
        SWEEP,
        "seeds",
    ),
    (
        "D29-seeds-strings",
        {"e.toml": EXPERIMENT.replace("seeds = 1", 'seeds = ["a"]')},
        SWEEP,
        "seeds",
    ),
    ("D29-duration-string", {"e.toml": EXPERIMENT.replace("5.0", '"long"')}, SWEEP, "duration_s"),
    (
        "D38-experiment-latency-nan",
        {"e.toml": EXPERIMENT + "[loss]\nlatency_s = nan\n"},
        SWEEP,
        "loss.latency_s: nan",
    ),
    ("D44-pers-empty", {}, ["experiment", "per-sweep", "--pers", "", "--out", "{d}/out"], "--pers"),
    (
        "D44-unreferenced-policy",
        {"e.toml": EXPERIMENT + '[policy.spare]\nbase = "paper"\nspeed_limit_mps = -1\n'},
        SWEEP,
        "e.toml: policy.spare.speed_limit_mps",
    ),
    # D21, D24, D45: vehicles and MAVLink URLs
    (
        "D21-deploy-port-99999",
        {"c.toml": CONVOY + '[v2v]\nauth = "off"\n'},
        [*DEPLOY[:8], "udpin:127.0.0.1:99999", *DEPLOY[9:]],
        "PORT in 1..65535",
    ),
    (
        "D21-vehicle-port-99999",
        {},
        ["vehicle", "--sim", "--id", "1", "--mavlink", "udpin:127.0.0.1:99999"],
        "PORT in 1..65535",
    ),
    (
        "D21-vehicle-start-nan",
        {},
        [
            "vehicle",
            "--sim",
            "--id",
            "1",
            "--mavlink",
            "udpin:127.0.0.1:{port}",
            "--start",
            "nan,0,0",
        ],
        "--start",
    ),
    (
        "D45-vehicle-max-rate-0",
        {},
        ["vehicle", "--sim", "--id", "1", "--mavlink", "udpin:127.0.0.1:{port}", "--max-rate", "0"],
        "--max-rate",
    ),
    (
        "D45-vehicle-port-taken",
        {},
        ["vehicle", "--sim", "--id", "1", "--mavlink", "udpin:127.0.0.1:{taken}"],
        "another vehicle on this port",
    ),
    # D20, D30, D45: field tools
    ("D20-abort-lo", {}, ["abort", "--iface", "lo"], "abort not sent on lo"),
    ("D20-send-lo", {}, ["bsm", "send", "--iface", "lo", "--count", "1"], "--iface lo"),
    (
        "D30-listen-timeout-nan",
        {},
        ["bsm", "listen", "--iface", "lo", "--timeout", "nan"],
        "--timeout: nan is out of range",
    ),
    ("D45-send-speed", {}, ["bsm", "send", "--iface", "lo", "--speed", "1e6"], "--speed"),
    ("D45-send-heading", {}, ["bsm", "send", "--iface", "lo", "--heading", "720"], "--heading"),
    ("D45-send-car", {}, ["bsm", "send", "--iface", "lo", "--compat-car", "999"], "--compat-car"),
    ("D45-train-M-0", {}, ["train", "--M", "0", "--out", "{d}/out"], "--M: 0 is out of range"),
    ("D25-train-rate-nan", {}, ["train", "--rate", "nan", "--out", "{d}/out"], "--rate"),
    ("D45-demo-per-2", {}, ["demo", "--per", "2"], "--per: 2 is out of range"),
    (
        "demo-link-unknown",
        {},
        ["demo", "--link", "mavlink,zenoh,ap-dds"],
        "--link: 'zenoh' is not one of mavlink, mavros",
    ),
    ("demo-link-count", {}, ["demo", "--link", "mavlink,ap-dds"], "--link: 2 links for 3 vehicles"),
    (
        "demo-apdds-px4",
        {},
        ["demo", "--link", "ap-dds", "--autopilot", "px4"],
        "--link: ap-dds drives ArduPilot vehicles",
    ),
    ("demo-px4dds-ardupilot", {}, ["demo", "--link", "px4-dds"], "--link: px4-dds drives PX4"),
    # D22, D28, D32: learned policy files
    (
        "D22-empty-npz",
        {"p.npz": b""},
        [*SIM, "--policy", "{d}/p.npz"],
        "p.npz: not a valid OpenConvoy policy export",
    ),
    (
        "D22-truncated-npz",
        {"p.npz": lambda p: (_npz(p), p.write_bytes(p.read_bytes()[:200]))},
        [*SIM, "--policy", "{d}/p.npz"],
        "p.npz",
    ),
    (
        "D22-nan-weights",
        {"p.npz": lambda p: _npz(p, nan=True)},
        [*SIM, "--policy", "{d}/p.npz"],
        "weights are not all finite",
    ),
    ("D22-corrupt-zip", {"p.zip": _zip}, [*SIM, "--policy", "{d}/p.zip"], SB3_LOADS),
    (
        "D22-export-corrupt-zip",
        {"p.zip": _zip},
        ["export", "{d}/p.zip", "--out", "{d}/out.npz"],
        "p.zip",
    ),
    (
        "D28-zip-bad-json",
        {"p.zip": lambda p: _zip(p, "{oops")},
        [*SIM, "--policy", "{d}/p.zip"],
        "is not valid JSON",
    ),
    (
        "D32-random-npz",
        {"p.npz": bytes(range(256)) * 8},
        [*SIM, "--policy", "{d}/p.npz"],
        "not a numpy .npz archive",
    ),
    # D27, D28, D43: logs
    (
        "D27-empty-log",
        {"log.csv": ",".join(COLUMNS) + "\n"},
        ["report", "{d}/log.csv"],
        "log.csv: the log has a header but no data rows",
    ),
    (
        "D27-garbage-log",
        {"log.csv": ",".join(COLUMNS) + "\ngarbage,line\n"},
        ["report", "{d}/log.csv"],
        "no data rows",
    ),
    (
        "D27-compare-garbage",
        {"log.csv": ",".join(COLUMNS) + "\ngarbage,line\n"},
        ["compare", "{d}/log.csv", "{d}/log.csv"],
        "no data rows",
    ),
    (
        "D28-bad-float",
        {"log.csv": _log([*GOOD_ROWS, {"t_s": 0.1, "vehicle_id": 0, "speed_mps": "fast"}])},
        ["report", "{d}/log.csv"],
        "log.csv:4: column speed_mps: 'fast' is not a number",
    ),
    (
        "D28-binary-log",
        {"log.csv": b"t_s,vehicle_id\n\xff\xfe\x00garbage"},
        ["report", "{d}/log.csv"],
        "not a text file",
    ),
    (
        "D28-binary-convoy",
        {"c.toml": b"\xff\xfe\x00\x01"},
        [*SIM, "--convoy", "{d}/c.toml"],
        "c.toml: not a text file",
    ),
    (
        "D43-unknown-mode",
        {"log.csv": _log([*GOOD_ROWS, {"t_s": 0.1, "vehicle_id": 0, "mode": "turbo"}])},
        ["report", "{d}/log.csv"],
        "column mode: 'turbo'",
    ),
    (
        "D43-inf-position",
        {"log.csv": _log([*GOOD_ROWS, {"t_s": 0.1, "vehicle_id": 0, "x_m": "inf"}])},
        ["report", "{d}/log.csv"],
        "column x_m: inf",
    ),
    (
        "D43-duplicate-rows",
        {"log.csv": _log([*GOOD_ROWS, GOOD_ROWS[0]])},
        ["report", "{d}/log.csv"],
        "appears more than once",
    ),
]


@pytest.mark.parametrize("files, argv, words", [p[1:] for p in PROBES], ids=[p[0] for p in PROBES])
def test_every_bad_input_is_one_line_and_exit_2(files, argv, words, tmp_path, capsys):
    for name, content in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if callable(content):
            content(path)
        elif isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
    held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a port a vehicle already holds
    held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    held.bind(("127.0.0.1", 0))
    subst = {"d": str(tmp_path), "port": str(free_port()), "taken": str(held.getsockname()[1])}
    try:
        code = main([a.format(**subst) for a in argv])
    finally:
        held.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("openconvoy: error: "), err
    assert words in err[0], err[0]
    assert not (tmp_path / "out").exists()  # nothing was written


def test_a_file_system_refusal_names_the_file_and_no_traceback(monkeypatch, capsys):
    # Permission errors cannot be provoked as root (the tests may run as root): an
    # unreadable input, as the file system reports it, is one line naming the file.
    import openconvoy.experiments.commands as commands

    def refuse(args):
        raise PermissionError(13, "Permission denied", "/data/run/log.csv")

    monkeypatch.setattr(commands, "report", refuse)
    assert main(["report", "/data/run/log.csv"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == "openconvoy: error: /data/run/log.csv: Permission denied"


def test_anything_else_is_a_bug_and_shows_its_traceback(monkeypatch):
    import openconvoy.experiments.commands as commands

    def bug(args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(commands, "presets", bug)
    with pytest.raises(ZeroDivisionError):
        main(["presets"])
