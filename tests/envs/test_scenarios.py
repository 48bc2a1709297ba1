"""Scenarios: the leader's speed phases, the oval, emergency braking, track files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from openconvoy.comms.geodesy import Origin, enu_to_geodetic
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.scenarios import (
    PAPER_PHASES,
    Scenario,
    make_scenario,
)
from openconvoy.envs.track import example_track_path, load_track, parse_track

DT = 0.05


def _drive_leader(scenario, seconds: float) -> dict[str, np.ndarray]:
    """Run only the leader's plant under the scenario's driver."""
    plant = BicyclePlant(scenario.presets[:1], DT)
    init = scenario.initial_state()
    plant.reset(init.x[:1], init.y[:1], init.heading[:1], init.speed[:1])
    scenario.reset(np.random.default_rng(0))
    rec: dict[str, list[float]] = {k: [] for k in ("t", "x", "y", "v", "h", "cmd")}
    for k in range(int(round(seconds / DT))):
        t = k * DT
        v, h = scenario.leader_command(
            t, float(plant.x[0]), float(plant.y[0]), float(plant.heading[0]), float(plant.speed[0])
        )
        plant.step(np.array([v]), np.array([h]))
        rec["t"].append(t + DT)
        rec["x"].append(float(plant.x[0]))
        rec["y"].append(float(plant.y[0]))
        rec["v"].append(float(plant.speed[0]))
        rec["h"].append(float(plant.heading[0]))
        rec["cmd"].append(v)
    return {k: np.array(v) for k, v in rec.items()}


@pytest.mark.parametrize("spec", ["paper", "track", "emergency-braking", "track-file:example"])
@pytest.mark.parametrize("n", [1, 2, 7])
def test_any_number_of_followers_start_at_the_desired_gaps(spec: str, n: int) -> None:
    sc = make_scenario(spec, n)
    assert isinstance(sc, Scenario)
    assert sc.n_vehicles == n + 1 and len(sc.presets) == n + 1
    init = sc.initial_state()
    gaps = np.hypot(np.diff(init.x), np.diff(init.y))
    if spec == "emergency-braking":
        # CACC: 2 m between bumpers + 0.6 s x 25 m/s, plus the half lengths (4.8 m cars).
        assert gaps == pytest.approx(2.0 + 0.6 * 25.0 + 4.8, abs=1e-9)
        assert init.speed == pytest.approx(25.0)
    elif spec == "paper":
        assert gaps == pytest.approx(15.0, abs=1e-9)
        assert init.speed == pytest.approx(0.0)
        assert [p.name for p in sc.presets[:4]] == ["1/10", "1/6", "1/10", "1/6"][: n + 1]
    else:
        # On a loop the arc gap is 15 m; the chord is shorter on the bends.
        assert np.all(gaps <= 15.0 + 1e-9) and np.all(gaps > 10.0)


def test_a_track_file_loop_holds_only_so_many_vehicles() -> None:
    # A file's loop has the length it has: 10 cars 15 m apart need more than its 130 m.
    with pytest.raises(ValueError, match="do not fit on a closed track"):
        make_scenario("track-file:example", 9)


def test_paper_leader_speed_phases() -> None:
    sc = make_scenario("paper")
    rec = _drive_leader(sc, 60.0)
    for _start, end, speed in PAPER_PHASES:
        last5 = (rec["t"] > end - 5.0) & (rec["t"] <= end)
        assert rec["v"][last5] == pytest.approx(speed, abs=0.01)
    # Changes are limited by the leader's acceleration limit (1 m/s²).
    accel = np.diff(rec["v"]) / DT
    assert np.abs(accel).max() <= sc.presets[0].accel_max_mps2 + 1e-9
    cmd_rate = np.abs(np.diff(rec["cmd"])) / DT
    assert cmd_rate.max() <= sc.presets[0].accel_max_mps2 + 1e-9
    # Straight road east: no lateral drift, 20 + 40 + 20 m minus the ramps.
    assert np.abs(rec["y"]).max() < 1e-9
    assert rec["x"][-1] == pytest.approx(80.0, abs=2.0)


def test_track_oval_closes_and_leader_follows_it() -> None:
    sc = make_scenario("track")
    path = sc.path
    assert path.closed
    pts = path.sample(0.1)
    # Two semicircles of radius 10 m: the oval is 20 m across and the loop closes.
    assert pts[:, 1].max() - pts[:, 1].min() == pytest.approx(20.0, abs=1e-3)
    straight = (path.length - 2 * math.pi * 10.0) / 2
    assert np.hypot(*(pts[0] - pts[-1])) < 0.11
    assert straight == pytest.approx(35.0, rel=1e-3)  # 2 followers 15 m apart + 5 m
    lap_s = path.length / 1.5
    rec = _drive_leader(sc, lap_s + 10.0)
    cruising = rec["t"] > 5.0
    assert rec["v"][cruising] == pytest.approx(1.5, abs=0.02)
    # Stays on the oval: distance to the path stays small, and it comes back round.
    off = [
        math.hypot(
            x - path.point_at(path.project(x, y))[0], y - path.point_at(path.project(x, y))[1]
        )
        for x, y in zip(rec["x"][::10], rec["y"][::10])
    ]
    assert max(off) < 0.3
    start = sc.initial_state()
    d_start = np.hypot(rec["x"] - start.x[0], rec["y"] - start.y[0])
    later = rec["t"] > lap_s / 2
    assert d_start[later].min() < 2.0  # completed a lap


def test_track_grows_for_long_convoys() -> None:
    sc = make_scenario("track", 20)
    assert sc.path.length >= 0.99 * 1.5 * 15.0 * 21
    init = sc.initial_state()
    assert np.hypot(np.diff(init.x), np.diff(init.y)).min() > 10.0


def test_emergency_braking_decelerates_at_6_mps2_to_a_stop() -> None:
    sc = make_scenario("emergency-braking")
    rec = _drive_leader(sc, 15.0)
    before = rec["t"] < 5.0
    assert rec["v"][before] == pytest.approx(25.0, abs=1e-6)
    braking = (rec["v"] < 22.0) & (rec["v"] > 3.0)
    decel = -np.diff(rec["v"])[braking[1:]] / DT
    assert np.median(decel) == pytest.approx(6.0, abs=0.1)
    assert decel.max() <= 6.0 + 0.2
    assert rec["v"][-1] < 0.05
    # Stopping distance: v^2 / (2 a) plus 25 m/s during the actuation delay and the speed
    # loop's lag (the plant tracks a ramp tau seconds late).
    car = sc.presets[0]
    x_brake = rec["x"][np.argmax(rec["t"] >= 5.0)]
    expected = 25.0**2 / 12.0 + 25.0 * (car.actuation_delay_s + car.speed_lag_s)
    assert rec["x"][-1] - x_brake == pytest.approx(expected, rel=0.05)


def _track_json(
    points: dict[str, tuple[float, float]], origin: Origin, closed: bool | None = None
) -> dict:
    def ll(name: str) -> dict[str, float]:
        lat, lon, _ = enu_to_geodetic(origin, *points[name])
        return {"lat": lat, "lon": lon}

    data = {
        "name": "test_loop",
        "straights": [
            {"start": ll("a"), "end": ll("b"), "speed": 2.0},
            {"start": ll("c"), "end": ll("d"), "speed": 1.0},
        ],
        "turns": [
            {"start": ll("b"), "end": ll("c"), "speed": 0.5, "direction": "left"},
            {"start": ll("d"), "end": ll("a"), "speed": 0.5, "direction": "left"},
        ],
        "center": {"lat": origin.lat_deg, "lon": origin.lon_deg},
    }
    if closed is not None:
        data["closed_loop"] = closed
    return data


ORIGIN = Origin(40.0, -75.0)
OVAL = {"a": (-15.0, -5.0), "b": (15.0, -5.0), "c": (15.0, 5.0), "d": (-15.0, 5.0)}


def test_track_file_geometry_and_speeds() -> None:
    track = parse_track(_track_json(OVAL, ORIGIN))
    assert track.path.closed
    assert track.origin == Origin(40.0, -75.0)
    # Two 30 m straights, two semicircles of radius 5 m (chord 10 m, 180° turns).
    assert track.path.length == pytest.approx(60.0 + 2 * math.pi * 5.0, rel=2e-3)
    assert track.speed_at(1.0) == 2.0
    assert track.speed_at(31.0) == 0.5
    assert track.speed_at(30.0 + 5 * math.pi + 1.0) == 1.0
    assert track.speed_at(track.path.length + 1.0) == 2.0  # wraps on a loop
    # The first turn bulges east of x = 15 (left turn from heading east).
    pts = track.path.sample(0.1)
    assert pts[:, 0].max() == pytest.approx(20.0, abs=0.02)
    assert pts[:, 0].min() == pytest.approx(-20.0, abs=0.02)


def test_track_file_right_turns_and_open_track() -> None:
    # The same loop driven clockwise: a -> d -> c -> b with right turns.
    cw = {"a": (-15.0, -5.0), "b": (-15.0, 5.0), "c": (15.0, 5.0), "d": (15.0, -5.0)}
    data = _track_json({"a": cw["a"], "b": cw["d"], "c": cw["c"], "d": cw["b"]}, ORIGIN)
    # Reverse the straights' direction for a clockwise loop.
    for s in data["straights"]:
        s["start"], s["end"] = s["end"], s["start"]
    data["straights"].reverse()
    data["turns"] = [
        {
            "start": data["straights"][0]["end"],
            "end": data["straights"][1]["start"],
            "speed": 0.5,
            "direction": "right",
        },
        {
            "start": data["straights"][1]["end"],
            "end": data["straights"][0]["start"],
            "speed": 0.5,
            "direction": "right",
        },
    ]
    track = parse_track(data)
    assert track.path.length == pytest.approx(60.0 + 2 * math.pi * 5.0, rel=2e-3)
    open_track = parse_track(_track_json(OVAL, ORIGIN, closed=False))
    assert not open_track.path.closed
    # Open: straight, turn, straight; the closing turn has no following straight.
    assert open_track.path.length == pytest.approx(60.0 + math.pi * 5.0, rel=2e-3)


def test_track_file_with_quarter_turns_closes() -> None:
    # A rectangle with rounded corners, as lab garage loops are drawn: four straights and
    # four 90° left turns of radius 3 m (chord 3√2 m).
    r = 3.0
    corners = [
        ((-10.0, -5.0 - r), (10.0, -5.0 - r)),
        ((10.0 + r, -5.0), (10.0 + r, 5.0)),
        ((10.0, 5.0 + r), (-10.0, 5.0 + r)),
        ((-10.0 - r, 5.0), (-10.0 - r, -5.0)),
    ]

    def ll(p: tuple[float, float]) -> dict[str, float]:
        lat, lon, _ = enu_to_geodetic(ORIGIN, *p)
        return {"lat": lat, "lon": lon}

    data = {
        "name": "rounded_rectangle",
        "straights": [{"start": ll(a), "end": ll(b), "speed": 1.0} for a, b in corners],
        "turns": [
            {
                "start": ll(corners[i][1]),
                "end": ll(corners[(i + 1) % 4][0]),
                "speed": 0.5,
                "direction": "left",
            }
            for i in range(4)
        ],
        "center": {"lat": ORIGIN.lat_deg, "lon": ORIGIN.lon_deg},
    }
    track = parse_track(data)
    assert track.path.length == pytest.approx(2 * 20.0 + 2 * 10.0 + 2 * math.pi * r, rel=2e-3)
    pts = track.path.sample(0.05)
    # Every arc ends where the next straight starts: no jumps along the loop.
    steps = np.hypot(*np.diff(np.vstack([pts, pts[:1]]), axis=0).T)
    assert steps.max() < 0.06
    assert pts[:, 0].max() == pytest.approx(10.0 + r, abs=1e-3)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.update(bogus=1), "unknown key.*bogus"),
        (lambda d: d["turns"][0].update(direction="sideways"), "direction"),
        (lambda d: d["straights"][0].pop("speed"), "missing key.*speed"),
        (lambda d: d["center"].update(alt=3), "unknown key.*alt"),
        (
            lambda d: d.update(
                straights=[{**d["straights"][0], "end": d["straights"][0]["start"]}], turns=[]
            ),
            "start and end coincide",
        ),
    ],
)
def test_track_file_is_strict(mutate, message: str) -> None:
    data = _track_json(OVAL, ORIGIN)
    mutate(data)
    with pytest.raises(ValueError, match=message):
        parse_track(data)


def test_track_file_scenario_leader_follows_the_file(tmp_path: Path) -> None:
    file = tmp_path / "loop.json"
    file.write_text(json.dumps(_track_json(OVAL, ORIGIN)))
    sc = make_scenario(f"track-file:{file}")
    assert sc.origin == ORIGIN
    track = load_track(file)
    rec = _drive_leader(sc, 60.0)
    off = []
    for x, y in zip(rec["x"][::5], rec["y"][::5]):
        px, py = track.path.point_at(track.path.project(x, y))
        off.append(math.hypot(x - px, y - py))
    assert max(off) < 0.35
    # Segment speeds: 2 m/s on the first straight, 0.5 m/s in the turn after it.
    on_first = (rec["x"] > -5.0) & (rec["x"] < 10.0) & (rec["y"] < -4.0) & (rec["t"] > 4.0)
    assert rec["v"][on_first] == pytest.approx(2.0, abs=0.05)
    in_turn = (rec["x"] > 17.0) & (np.abs(rec["y"]) < 2.0)
    assert in_turn.any() and rec["v"][in_turn].max() < 0.6


def test_example_track_ships_and_loads() -> None:
    path = example_track_path()
    assert path.is_file() and path.suffix == ".json"
    data = json.loads(path.read_text())
    assert set(data) == {"name", "straights", "turns", "center"}
    track = load_track(path)
    assert track.path.closed and track.path.length > 50.0


def test_unknown_scenario_names_the_choices() -> None:
    with pytest.raises(ValueError, match="paper.*track.*emergency-braking"):
        make_scenario("highway")
    with pytest.raises(FileNotFoundError, match="no such track file"):
        make_scenario("track-file:/nonexistent.json")
    with pytest.raises(ValueError, match="at least one follower"):
        make_scenario("paper", 0)


def test_a_built_scenario_is_changed_only_by_building_a_new_one_validated_again() -> None:
    from openconvoy.core.errors import ConfigError
    from openconvoy.core.spacing import SpacingConfig

    track = make_scenario("track")
    wider = track.with_changes(spacing=SpacingConfig("constant-distance", distance_m=12.0))
    assert wider.spacing.distance_m == 12.0 and track.spacing.distance_m != 12.0  # untouched
    # Gaps that do not fit on the closed track are refused, as at construction.
    with pytest.raises(ConfigError, match="do not fit"):
        track.with_changes(spacing=SpacingConfig("constant-distance", distance_m=500.0))


@pytest.mark.parametrize("closed", [False, True])
def test_a_path_of_one_repeated_point_is_refused(closed: bool) -> None:
    """Repeated vertices are dropped (a zero-length segment has no heading); a path left
    with fewer than two points is a config error, not numpy's empty ``argmin``."""
    from openconvoy.core.errors import ConfigError
    from openconvoy.envs.path import Path as RoadPath

    with pytest.raises(ConfigError, match="two distinct"):
        RoadPath(np.array([[3.0, 4.0], [3.0, 4.0], [3.0, 4.0 + 1e-12]]), closed=closed)
    kept = RoadPath(np.array([[0.0, 0.0], [0.0, 0.0], [5.0, 0.0], [5.0, 0.0]]), closed=closed)
    assert kept.points.tolist() == [[0.0, 0.0], [5.0, 0.0]]
    assert kept.project(2.0, 1.0) == 2.0
