"""Issue 22 item 6, the envs' rows of D67-D69: bad arguments and actions give one
ConfigError / ValueError naming the value, bounds come with their message. At aea1a73:
a (3,) action drove with its third value dropped, the other bad actions became silent
policy-error stops, unknown agent keys were ignored, ``step`` before ``reset`` said
"finished episode", ``max_time_s=nan`` raised a raw ``cannot convert float NaN to
integer``, -1 and ``VectorConvoyEnv(1.5)`` were accepted, ``VectorConvoyEnv(10**7)`` and
``ConvoyEnv(n_followers=5000)`` ran for minutes, ``highway-cut-in:cut_in_at_s=nan``
never cut in."""

from __future__ import annotations

import numpy as np
import pytest

from openconvoy.core.errors import ConfigError
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv


@pytest.mark.parametrize(
    "action",
    [np.zeros(3), np.zeros(1), np.zeros((2, 2)), 1.0, "go", None, np.array([1, 2], dtype=object)],
    ids=["3", "1", "2x2", "scalar", "str", "none", "object"],
)
def test_an_action_that_is_not_two_numbers_is_named(action: object) -> None:
    env = ConvoyEnv()
    env.reset(seed=0)
    actions = {"follower_1": np.zeros(2, np.float32), "follower_2": action}
    with pytest.raises(ValueError, match=r"action of follower_2: expected shape \(2,\)") as e:
        env.step(actions)
    assert "\n" not in str(e.value)


def test_unknown_agents_and_step_before_reset() -> None:
    env = ConvoyEnv()
    with pytest.raises(RuntimeError, match="before reset"):
        env.step({a: np.zeros(2) for a in env.possible_agents})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"unknown agents \['follower_9'\]"):
        env.step({**{a: np.zeros(2) for a in env.possible_agents}, "follower_9": np.zeros(2)})
    # A non-finite action is still the policy's error: that follower stops, nothing raises.
    env.step({"follower_1": np.array([np.nan, 0.0]), "follower_2": np.zeros(2)})
    assert env.safety_events[0][1:] == (1, "policy error: non-finite action nan, 0.0")


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: ConvoyEnv(max_time_s=float("nan")), "max_time_s"),
        (lambda: ConvoyEnv(max_time_s=-1), "max_time_s"),
        (lambda: ConvoyEnv(n_followers=5000), r"n_followers must be in 1\.\.1000"),
        (lambda: ConvoyEnv(n_followers=1.5), "n_followers: expected an integer"),
        (lambda: VectorConvoyEnv(1.5), "num_envs: expected an integer"),
        (lambda: VectorConvoyEnv("2"), "num_envs: expected an integer"),
        (lambda: VectorConvoyEnv(10**7), r"num_envs must be in 1\.\.1000000"),
        (lambda: VectorConvoyEnv(2**31), r"num_envs must be in 1\.\.1000000"),
        (lambda: VectorConvoyEnv(2, max_time_s=float("nan")), "max_time_s"),
        (lambda: ConvoyEnv("highway-cut-in:cut_in_at_s=nan"), "cut_in_at_s must be a finite"),
        (lambda: ConvoyEnv("highway-cut-in:cut_in_at_s=-5"), "cut_in_at_s must be >= 0"),
        (lambda: ConvoyEnv("highway-cut-in:traffic=100000"), "traffic must be at most 500"),
    ],
)
def test_bad_env_arguments_are_one_config_error(make, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as e:
        make()
    assert "\n" not in str(e.value)


def test_vector_env_safety_events_index_and_close() -> None:
    vec = VectorConvoyEnv(2)
    vec.reset(seed=0)
    assert vec.safety_events(1) == []
    for bad in (2, -1, 1.0):
        with pytest.raises(ValueError, match="safety_events"):
            vec.safety_events(bad)  # type: ignore[arg-type]
    vec.close()
