"""Issue 22, the PX4 start stall, replayed from the firmware run (tests/data/px4_start_stall).

The leader's broadcasts (each row where its ``msgs_sent`` counter rose: the state it
sent) and follower 1's own states, as logged on PX4 SIH rovers, go through a
``ConvoyMember`` and the ``paper`` policy tick by tick, as ``core.tick`` runs them on a
vehicle. On the firmware the follower commanded 0 m/s for 10.1 s after the leader moved
off (its spacing error read -15 m while the gap grew to 24 m); replayed with the trail of
aea1a73 it commands 0 m/s for 6.7 s after the leader passes the desired gap. With the
trail that smooths fixes along the reported motion, lays breadcrumbs on progress and
extends behind the oldest one along the reported heading, it drives off at once.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from openconvoy.core.member import ConvoyMember
from openconvoy.core.state import VehicleState
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.policies import load_policy

DATA = Path(__file__).resolve().parents[1] / "data" / "px4_start_stall"
PRESETS = ("1/10", "1/6", "1/10")  # the run's convoy.toml


def _rows(vehicle: int) -> list[dict[str, str]]:
    with open(DATA / f"vehicle_{vehicle}.csv", newline="") as f:
        return list(csv.DictReader(f))


def _state(row: dict[str, str]) -> VehicleState:
    return VehicleState(
        int(row["vehicle_id"]),
        float(row["t_s"]),
        float(row["x_m"]),
        float(row["y_m"]),
        float(row["speed_mps"]),
        float(row["heading_rad"]),
        float(row["accel_mps2"]),
        0.0,
        float(row["length_m"]),
    )


def replay() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Follower 1's tick times (s), its replayed speed commands (m/s) and the centre gap
    (m) to the leader by the logged positions."""
    policy = load_policy("paper")
    assert policy.member_config is not None
    presets = [vehicle_preset(p) for p in PRESETS]
    member = ConvoyMember(
        1,
        3,
        policy.member_config,
        [p.length_m for p in presets],
        [p.decel_max_mps2 for p in presets],
    )
    lead = _rows(0)
    sent = [
        _state(r)
        for k, r in enumerate(lead)
        if k == 0 or int(r["msgs_sent"]) > int(lead[k - 1]["msgs_sent"])
    ]
    times, cmds, gaps = [], [], []
    j = 0
    last_lead = sent[0]
    for row in _rows(1):
        own = _state(row)
        inbox = []
        while j < len(sent) and sent[j].t <= own.t:
            inbox.append(sent[j])
            j += 1
        if inbox:
            last_lead = inbox[-1]
        member.observe_own(own)
        member.receive_all(inbox, own.t)
        action = policy.act(member.sense(own.t).observation)
        times.append(own.t)
        cmds.append(float(action[0]))
        gaps.append(float(np.hypot(last_lead.x - own.x, last_lead.y - own.y)))
    return np.array(times), np.array(cmds), np.array(gaps)


def test_the_follower_drives_off_once_the_leader_is_past_the_desired_gap() -> None:
    t, cmd, gap = replay()
    logged = np.array([float(r["cmd_speed_mps"]) for r in _rows(1)])
    # The leader is past the 15 m desired gap (+0.5 m) from here on ...
    away = np.flatnonzero(gap > 15.5)
    t_away = t[away[0]]
    assert np.all(gap[away[0] :] > 15.5)
    after = t >= t_away
    # ... the firmware run's follower commanded 0 m/s for more than 6 s of that ...
    assert (logged[after] < 0.05).sum() * 0.05 > 6.0
    # ... the replay commands it to drive within 0.5 s, and never stops it again.
    held = after & (cmd < 0.05)
    assert held.sum() * 0.05 <= 0.5
    assert np.all(cmd[t >= t_away + 0.5] > 0.3)
