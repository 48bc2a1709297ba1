"""The training environments' reward terms (``train.shaping``), the from-scratch defaults
they come with, and validation's path error."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import PATH_FEATURES
from openconvoy.envs.scenarios import make_scenario
from openconvoy.train.cli import wall_clock
from openconvoy.train.config import TrainConfig
from openconvoy.train.randomization import (
    TRAIN_SHAPING,
    EnvSpec,
    Randomization,
    RandomizedConvoyEnv,
)
from openconvoy.train.shaping import Shaping
from openconvoy.train.validate import PATH_KEY, path_error_p95
from openconvoy.train.vecenv.randomized import RandomizedVectorVecEnv

LAYOUT = MemberConfig().layout
XT = LAYOUT.path_offset + PATH_FEATURES.index("cross_track")
VALID = LAYOUT.path_offset + PATH_FEATURES.index("valid")
HEADING = LAYOUT.path_offset + PATH_FEATURES.index("heading_error")


def test_bonus_pays_for_the_last_metre_on_the_trail() -> None:
    s = Shaping(weight=2.0, gap_scale_m=1.0, path_scale_m=4.0, heading_scale_rad=0.5)
    obs = np.zeros((5, LAYOUT.size), np.float32)
    obs[:, VALID] = 1.0
    obs[:, XT] = [0.0, -2.0, 0.0, 9.0, 1.0]
    obs[:, HEADING] = [0.0, -0.25, 0.0, 0.0, 1.0]
    obs[4, VALID] = 0.0  # no trail heard: nothing to be off
    bonus = s.bonus(LAYOUT, np.array([0.0, 0.25, 3.0, 0.0, np.nan]), obs)
    # in place; 0.75 of the gap x half the offset x half the heading; too far behind;
    # beside the road; NaN error and no trail
    assert bonus == pytest.approx([2.0, 2.0 * 0.75 * 0.5 * 0.5, 0.0, 0.0, 2.0])
    assert not Shaping().active and Shaping().bonus(LAYOUT, np.ones(5), obs).tolist() == [0] * 5


def test_both_training_paths_add_the_bonus_to_the_simulators_reward() -> None:
    r = Randomization(vehicles=())
    shaped, plain = (
        EnvSpec(base_policy="", max_time_s=5.0, shaping=sh) for sh in (TRAIN_SHAPING, Shaping())
    )
    envs = [RandomizedVectorVecEnv(spec, r, n_convoys=3, n_worlds=1) for spec in (shaped, plain)]
    for env in envs:
        env.seed(3)
        env.reset()
    act = np.random.default_rng(0).uniform(-1, 1, size=(6, 2)).astype(np.float32)
    for _ in range(20):
        (obs, r_s, _, info), (_, r_p, _, _) = (env.step(act) for env in envs)
        err = np.array([i["platooning_error_m"] for i in info])
        assert r_s - r_p == pytest.approx(TRAIN_SHAPING.bonus(LAYOUT, err, obs), abs=1e-5)
    assert (r_s - r_p).max() > 0.1  # the bonus is there, not zero
    # The per-convoy path (SuperSuit's) does the same.
    single = [RandomizedConvoyEnv(spec, r) for spec in (shaped, plain)]
    (obs_d, _), _ = (e.reset(seed=1) for e in single)
    a = {agent: np.array([0.2, 0.0], np.float32) for agent in obs_d}
    (obs_d, rew_s, _, _, infos), (_, rew_p, _, _, _) = (e.step(a) for e in single)
    for agent in obs_d:
        expected = TRAIN_SHAPING.bonus(
            LAYOUT, np.array(infos[agent]["platooning_error_m"]), obs_d[agent]
        )
        assert rew_s[agent] - rew_p[agent] == pytest.approx(float(expected), abs=1e-9)


def test_both_kinds_train_with_the_bonus_unless_a_config_turns_it_off() -> None:
    assert EnvSpec(base_policy="").shaping == TRAIN_SHAPING == EnvSpec().shaping
    assert EnvSpec().extra.active and not EnvSpec(shaping=Shaping()).extra.active


def test_default_validation_scores_per_zero_too() -> None:
    assert TrainConfig().validation_pers == (0.0, 0.3, 0.6)


def test_path_error_sees_a_follower_beside_the_road() -> None:
    """The platooning error cannot: a follower 3 m beside its place still has its gap
    (to within 0.3 m); the path error is 3 m."""
    scene = make_scenario("paper")
    x0 = float(scene.path.point_at(0.0)[0])
    T = 50
    log = {
        "vehicle_id": np.tile(np.arange(3), T),
        "x_m": np.tile([x0 + 40.0, x0 + 25.0, x0 + 10.0], T),
        "y_m": np.tile([0.0, 3.0, 0.0], T),
    }
    assert path_error_p95(log, scene) == pytest.approx(3.0, abs=0.01)
    log["y_m"] = np.zeros(3 * T)
    assert path_error_p95(log, scene) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(path_error_p95(log, object()))
    assert PATH_KEY == "p95_path_error_m"


def test_budget_takes_seconds_minutes_hours() -> None:
    assert [wall_clock(t) for t in ("900", "900s", "15m", "1.5h")] == [900, 900, 900, 5400]
    for bad in ("15 min", "-3m", "0", "nan", "m"):
        with pytest.raises(argparse.ArgumentTypeError, match="duration"):
            wall_clock(bad)
