"""The Python API as users of Gymnasium and PettingZoo expect it: a PER where a loss is
taken, and the single-agent spaces of the batched env."""

from __future__ import annotations

import numpy as np
import pytest

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv


def _episode(env: ConvoyEnv, seed: int = 3, steps: int = 120) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    out = []
    for _ in range(steps):
        obs, *_ = env.step({a: np.array([2.0, 0.0], dtype=np.float32) for a in env.agents})
        out.append(np.concatenate([obs[a] for a in sorted(obs)]))
    return np.array(out)


def test_a_packet_error_rate_is_a_loss_config_of_that_rate():
    reference = ConvoyEnv(loss=LossConfig(per=0.4))
    by_per, by_loss = ConvoyEnv(per=0.4), ConvoyEnv(loss=0.4)
    assert by_per.loss == by_loss.loss == reference.loss
    np.testing.assert_array_equal(_episode(by_per), _episode(reference))
    np.testing.assert_array_equal(_episode(by_loss), _episode(reference))
    # per replaces a config's rate and keeps the rest of it.
    ge = ConvoyEnv(loss=LossConfig(model="gilbert-elliott", mean_burst_s=0.5), per=0.3)
    assert ge.loss == LossConfig(per=0.3, model="gilbert-elliott", mean_burst_s=0.5)
    assert _episode(ConvoyEnv(per=0.0)).shape == _episode(ConvoyEnv()).shape


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"loss": 0.2, "per": 0.3}, "per=... or loss=..., not both"),
        ({"loss": "0.2"}, "loss must be a LossConfig or a packet error rate, got str"),
        ({"per": 1.5}, "per must be in [0, 1], got 1.5"),
        ({"per": "high"}, "per must be a number in [0, 1], got str"),
    ],
)
def test_a_bad_rate_is_one_config_error(kwargs, message):
    with pytest.raises(ConfigError) as err:
        ConvoyEnv(**kwargs)
    assert message in str(err.value)


def test_the_batched_env_has_gymnasium_spaces_and_per_convoy_rates():
    env = VectorConvoyEnv(3, per=[0.0, 0.3, 0.6])
    assert [c.per for c in env.losses] == [0.0, 0.3, 0.6]
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    assert env.single_observation_space.shape == (obs.shape[-1],)
    assert all(env.single_observation_space.contains(o) for o in obs.reshape(-1, obs.shape[-1]))
    single = ConvoyEnv()
    agent = single.possible_agents[0]
    assert env.single_observation_space == single.observation_space(agent)
    assert env.single_action_space == single.action_space(agent)
    action = env.action_space.sample()
    assert action.shape == (3, env.n_vehicles - 1, 2)
    env.step(action)
    assert VectorConvoyEnv(2, loss=0.2).losses == [LossConfig(per=0.2)] * 2
    with pytest.raises(ConfigError, match="one packet error rate per convoy"):
        VectorConvoyEnv(2, per=[0.1])
