"""``sim`` with the firmware-fitted preset against a convoy run on real ArduPilot firmware.

tests/data/sitl/convoy/ holds the deploy logs of three ArduPilot Rover 4.7 SITL instances
driven by ``openconvoy deploy --policy paper`` (the ``paper`` scenario, BSMs over IPv6
multicast on a veth pair). The simulation runs the same scenario and policy with all three
vehicles ``ardupilot-rover``; its V2V latency is set so the followers see the predecessor's
messages as old as they were on the firmware run (``pred_msg_age_s`` mean 0.072 / 0.079 s
there, 0.075 s in sim at ``--latency 0.05``; 0.025 s without it).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from openconvoy.cli import main
from openconvoy.logs import read_log

REPO_ROOT = Path(__file__).resolve().parents[2]
CONVOY_DIR = REPO_ROOT / "tests" / "data" / "sitl" / "convoy"
RECORDED_RUNS = ("vx-fixed-1", "vx-fixed-2")
LATENCY_S = "0.05"


def _convoy_dir() -> Path:
    if not (CONVOY_DIR / "convoy.toml").is_file():
        raise FileNotFoundError(f"firmware convoy logs not found at {CONVOY_DIR}")
    return CONVOY_DIR


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory) -> Path:
    """The paper scenario in sim, three ardupilot-rover vehicles, as the firmware run."""
    tmp = tmp_path_factory.mktemp("firmware-convoy")
    convoy = tmp / "convoy.toml"
    recorded = (_convoy_dir() / "convoy.toml").read_text()
    origin = next(line for line in recorded.splitlines() if line.startswith("origin"))
    convoy.write_text(
        '[convoy]\nname = "sitl-sim"\nscenario = "paper"\n'
        'vehicles = ["ardupilot-rover", "ardupilot-rover", "ardupilot-rover"]\n'
        f"{origin}\n"
    )
    out = tmp / "sim"
    assert (
        main(
            [
                "sim",
                "--convoy",
                str(convoy),
                "--policy",
                "paper",
                "--latency",
                LATENCY_S,
                "--out",
                str(out),
                "--quiet",
                "--no-plots",
            ]
        )
        == 0
    )
    return out


def test_sim_sees_messages_as_old_as_the_firmware_run(sim_run: Path) -> None:
    def ages(path: Path) -> list[float]:
        log = read_log(path)
        out = []
        for vid in (1, 2):
            a = np.asarray(log["pred_msg_age_s"][log["vehicle_id"] == vid], dtype=float)
            out.append(float(np.nanmean(a)))
        return out

    sim_ages = ages(sim_run)
    for run in RECORDED_RUNS:
        for got, want in zip(sim_ages, ages(_convoy_dir() / run)):
            assert got == pytest.approx(want, abs=0.015)


@pytest.mark.parametrize("run", RECORDED_RUNS)
def test_sim_p95_and_string_stability_match_the_firmware_convoy(
    run: str, sim_run: Path, tmp_path: Path, capsys
) -> None:
    recorded = _convoy_dir() / run
    lengths = str(_convoy_dir() / "convoy.toml")
    # The firmware run's figures, as `openconvoy report` measures them.
    assert (
        main(
            ["report", str(recorded), "--convoy", lengths, "--out", str(tmp_path / "metrics.json")]
        )
        == 0
    )
    reported = json.loads((tmp_path / "metrics.json").read_text())
    capsys.readouterr()
    assert (
        main(
            [
                "compare",
                str(recorded),
                str(sim_run),
                "--convoy",
                lengths,
                "--out",
                str(tmp_path / "cmp.json"),
            ]
        )
        == 0
    )
    print(capsys.readouterr().out)
    m = json.loads((tmp_path / "cmp.json").read_text())["metrics"]
    p95, ss = m["p95_platooning_error_m"], m["string_stability"]
    assert p95["a"] == pytest.approx(reported["p95_platooning_error_m"])
    assert ss["a"] == pytest.approx(reported["string_stability"])
    # Firmware: p95 0.333 / 0.331 m, string stability 1.33 / 1.35.
    assert abs(p95["b"] - p95["a"]) <= 0.10 * p95["a"], p95
    assert (ss["a"] > 1.0) == (ss["b"] > 1.0), ss
    assert m["collisions"]["b"] == 0
