"""Ranging sensors in VectorConvoyEnv against ConvoyEnv (``_compare`` of
``test_vector_env``): the forward rangefinder's noisy reading feeds the ladder's ACC
fallback, the ranging override and the braking-aware emergency rule the same way in both,
on the paper, track and emergency-braking scenarios under loss."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from test_vector_env import _compare

from openconvoy.comms.loss import LossConfig
from openconvoy.core.ladder import LadderConfig
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
from openconvoy.envs.ranging_noise import ranging_normals
from openconvoy.envs.vehicles import VEHICLE_PRESETS, RangingSensor
from openconvoy.policies.spec import load_policy
from tests.python_world import python_world  # noqa: F401 - reads the Python world

LADDER = {"ladder": LadderConfig(enabled=True)}
RADAR = RangingSensor(max_range_m=150.0, range_noise_m=0.1, range_rate_noise_mps=0.1)


def _sensing(name: str, n: int = 3, sensor: RangingSensor | None = None) -> list:
    """A convoy of ``n`` ``name`` vehicles whose followers carry a ranging sensor."""
    p = VEHICLE_PRESETS[name]
    return [p] + [p.with_ranging(sensor)] * (n - 1)


def _readings(scenario: str, presets: list | None, per: float, member: dict, steps: int) -> tuple:
    """(follower-ticks with a reading, modes seen, final x m) of one batched run of the
    paper policy."""
    mc = dataclasses.replace(load_policy("paper").member_config, **member)
    vec = VectorConvoyEnv(1, scenario, member_config=mc, loss=LossConfig(per=per),
                          vehicle_presets=presets, autoreset=False)  # fmt: skip
    obs, _ = vec.reset(seed=10)
    policy, seen, modes = load_policy("paper"), 0, set()
    for _ in range(steps):
        obs, _, term, _, info = vec.step(policy.act_batch(obs))
        seen += int((~np.isnan(vec.ranging.reading[0])).sum())
        modes |= set(info["mode"].ravel().tolist())
        if term.any():
            break
    return seen, modes, vec.own[0].copy()


def test_paper_whole_episode_under_loss_with_the_emergency_rule_on_ranging() -> None:
    modes = _compare("paper", B=2, per=0.3, vehicle_presets=_sensing("1/10"))
    assert set(modes) == {"coop"}
    assert _readings("paper", _sensing("1/10"), 0.3, {}, 200)[0] == 200 * 2  # always in range


def test_paper_ladder_follows_the_ranging_reading_under_heavy_loss() -> None:
    sensing = _compare("paper", B=2, per=0.9, member=LADDER, vehicle_presets=_sensing("1/10"),
                       steps=500)  # fmt: skip
    blind = _compare("paper", B=2, per=0.9, member=LADDER, steps=500)
    assert sensing["degraded"] > 100 and sensing["stop"] > 0
    assert sensing == blind  # the same rungs (they go by message ages) ...
    presets = _sensing("1/10")
    seen, _, x_sensing = _readings("paper", presets, 0.9, LADDER, 500)
    _, _, x_blind = _readings("paper", None, 0.9, LADDER, 500)
    assert seen > 0 and np.abs(x_sensing - x_blind).max() > 1e-3  # ... other speeds


def test_full_size_cars_on_the_track_under_loss_and_gps_noise() -> None:
    """The sensor measures the true gap, whatever the GPS fixes say."""
    modes = _compare("track", B=1, per=0.9, member=LADDER, vehicle_presets=_sensing("full-size"),
                     gps_noise_m=0.5)  # fmt: skip
    assert modes["degraded"] > 0


def test_emergency_braking_with_a_radar_under_loss() -> None:
    presets = _sensing("full-size", sensor=RADAR)
    _compare("emergency-braking", B=2, per=0.3, vehicle_presets=presets)
    modes = _compare("emergency-braking", B=1, per=0.8, member=LADDER, vehicle_presets=presets)
    assert modes["degraded"] > 0
    seen, _, _ = _readings("emergency-braking", presets, 0.3, {}, 300)
    assert seen == 300 * 2  # the radar sees the car ahead throughout


def test_a_short_sensor_reads_only_in_range() -> None:
    """60 m on full-size cars at highway gaps: some ticks in range, some out."""
    presets = _sensing("full-size", n=4, sensor=RangingSensor(max_range_m=60.0))
    _compare("emergency-braking", B=1, per=0.2, vehicle_presets=presets)
    seen, _, _ = _readings("emergency-braking", presets, 0.2, {}, 300)
    assert 0 < seen < 300 * 3


def test_the_ranging_override_resists_a_forged_predecessor() -> None:
    """Authentication off, a forger puts vehicle 1 a kilometre ahead of where it is: the
    V2V gap of follower 2 jumps, its sensor's does not, so it follows by ranging."""
    kw = {"faults": ["forge:1@5"], "auth": False, "n_followers": 3, "member": LADDER}
    modes = _compare("paper", B=2, per=0.0, vehicle_presets=_sensing("1/10", 4), steps=400, **kw)
    assert modes["degraded"] > 0 and "failsafe" not in modes


def test_the_emergency_rule_fires_on_the_sensors_closing_speed() -> None:
    """A forged leader chased (authentication off): the followers close in on the real
    one and the braking-aware rule stops them on what the sensor reads, at the same tick."""
    modes = _compare("paper", B=2, per=0.2, vehicle_presets=_sensing("1/10"),
                     faults=["forge:0@5"], auth=False, steps=400)  # fmt: skip
    assert modes["failsafe"] > 0


def test_readings_are_noisy_and_keyed_per_episode() -> None:
    """The batched reading is ConvoyWorld's reading (its noise included) at tick 0 of
    two seeds, and differs between them."""
    presets = _sensing("1/10", sensor=RangingSensor(range_noise_m=0.5))
    out = []
    for seed in (1, 2):
        env = ConvoyEnv("paper", vehicle_presets=presets)
        env.reset(seed=seed)
        want = env.sim.ranging_readings()
        vec = VectorConvoyEnv(1, "paper", vehicle_presets=presets)
        vec.reset(seed=seed)
        vec.ranging.read(vec.own, vec.step_count)
        got = vec.ranging.reading[:, 0, 1:].T
        np.testing.assert_allclose(got, [want[1], want[2]], rtol=0, atol=1e-12)
        got = got.tolist()
        out.append(got)
    assert out[0] != out[1]
    z = np.array([ranging_normals(2**62 + 3, k) for k in range(4000)])
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1.0) < 0.05


def test_sensors_step_stage_by_stage() -> None:
    assert VectorConvoyEnv(1, vehicle_presets=_sensing("1/10"))._fused is None
    assert VectorConvoyEnv(1)._fused is not None
