"""PPO with Ray RLlib on the multi-agent PettingZoo convoy env: every follower runs one
shared policy, trained on a reward plug-in and an observation-features plug-in, then saved
and restored from a checkpoint (needs ``ray[rllib]``: ``make test`` builds ``.venv-rllib``,
since RLlib pins its own gymnasium).

The env is ``RandomizedConvoyEnv``, what ``openconvoy train`` learns on: a PettingZoo
``ParallelEnv`` of ``ConvoyEnv`` whose world (loss, latency, GPS noise, vehicles) is drawn
at every reset and whose actions are residuals in [-1, 1] on the paper's controller. Its
reward here is ``examples/my_reward.py:Smooth`` and its observation carries
``examples/my_features.py:GapRatio``'s two numbers; RLlib sees it through its own
PettingZoo wrapper (``ParallelPettingZooEnv``). A few iterations learn little: raise
``--iterations`` and ``--batch`` for a policy worth keeping.

    make rllib && . .venv-rllib/bin/activate
    python examples/train_rllib.py [--iterations 3] [--batch 400] [--out runs/rllib-example]
    python examples/train_rllib.py --restore runs/rllib-example/checkpoint --iterations 1
    python examples/train_rllib.py --critic central   # MAPPO-style: a centralised critic

It prints one line per iteration (``iteration 2 env_steps 800 return 98.8``: env steps so
far, the mean return of the episodes that ended in it, summed over the followers), the
shared policy's greedy action on a fixed observation after saving, and the same line after
restoring, so the two can be compared. Sampling and learning run in this process (no
env-runner or learner actors); the local Ray it starts for RLlib listens on 127.0.0.1 only,
without the dashboard, in a folder of its own, and is shut down on the way out.

``--critic central`` trains MAPPO-style: each follower's observation is its own followed by
the other followers' (``CentralObservations``), the value function reads all of it and the
actor its own part only (``CentralCriticModule``), so the trained actor needs nothing but
its own observation where it runs. With ``--critic own`` (the default) both read the
follower's own observation (RLlib's default PPO module).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import gymnasium
import numpy as np
import ray
import torch
from pettingzoo import ParallelEnv
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.core.rl_module.torch import TorchRLModule
from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    EPISODE_RETURN_MEAN,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
)
from ray.tune.registry import register_env

from openconvoy.train.randomization import EnvSpec, Randomization, RandomizedConvoyEnv

EXAMPLES = Path(__file__).resolve().parent
REWARD = f"{EXAMPLES / 'my_reward.py'}:Smooth?weight=0.2"
FEATURES = f"{EXAMPLES / 'my_features.py'}:GapRatio"
POLICY = "shared"
ENV = "openconvoy-randomized"
HIDDEN = [64, 64]


class CentralObservations(ParallelEnv):
    """A PettingZoo env whose agents each observe their own observation followed by the
    others' (in ``possible_agents`` order; zeros for one that has left): the centralised
    critic's input. Everything else passes through."""

    def __init__(self, env: ParallelEnv) -> None:
        self.env = env
        self.possible_agents = list(env.possible_agents)
        self.agents: list[str] = []
        self.metadata = env.metadata
        self.own_size = env.observation_space(self.possible_agents[0]).shape[0]
        size = self.own_size * len(self.possible_agents)
        self._space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._space

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        return self.env.action_space(agent)

    def _central(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        zero = np.zeros(self.own_size, dtype=np.float32)
        return {
            a: np.concatenate(
                [o, *(obs.get(b, zero) for b in self.possible_agents if b != a)]
            ).astype(np.float32)
            for a, o in obs.items()
        }

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.env.agents)
        return self._central(obs), infos

    def step(self, actions: dict):
        obs, rewards, term, trunc, infos = self.env.step(actions)
        self.agents = list(self.env.agents)
        return self._central(obs), rewards, term, trunc, infos

    def close(self) -> None:
        self.env.close()


def _mlp(sizes: list[int]) -> torch.nn.Sequential:
    """Linear layers of ``sizes`` with tanh between them."""
    layers: list[torch.nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes, sizes[1:])):
        layers += [torch.nn.Linear(a, b)] + ([torch.nn.Tanh()] if i < len(sizes) - 2 else [])
    return torch.nn.Sequential(*layers)


class CentralCriticModule(TorchRLModule, ValueFunctionAPI):
    """MAPPO-style PPO module: the actor reads the follower's own observation (the first
    ``model_config["own_size"]`` numbers), the critic the whole central observation."""

    def setup(self) -> None:
        self.own_size = int(self.model_config["own_size"])
        n_act = self.action_space.shape[0]
        hidden = list(self.model_config.get("hidden", HIDDEN))
        self.actor = _mlp([self.own_size, *hidden, 2 * n_act])  # Gaussian mean, log std
        self.critic = _mlp([self.observation_space.shape[0], *hidden, 1])

    def _forward(self, batch: dict, **kwargs) -> dict:
        own = batch[Columns.OBS][..., : self.own_size]
        return {Columns.ACTION_DIST_INPUTS: self.actor(own)}

    def compute_values(self, batch: dict, embeddings=None) -> torch.Tensor:
        return self.critic(batch[Columns.OBS]).squeeze(-1)


def make_env(env_config: dict) -> ParallelPettingZooEnv:
    """The convoy env as RLlib wants it: ``RandomizedConvoyEnv`` (two followers, the
    plug-ins above, episodes of ``env_config["seconds"]`` s; central observations with
    ``env_config["critic"] == "central"``) in RLlib's ``ParallelPettingZooEnv``."""
    spec = EnvSpec(
        n_followers=2, reward_fn=REWARD, obs_features=FEATURES, max_time_s=env_config["seconds"]
    )
    env: ParallelEnv = RandomizedConvoyEnv(spec, Randomization())
    if env_config["critic"] == "central":
        env = CentralObservations(env)
    return ParallelPettingZooEnv(env)


def build_config(batch: int, seconds: float, critic: str, seed: int) -> PPOConfig:
    """PPO on the new API stack: one policy for every follower, ``batch`` env steps per
    iteration, sampling and learning in this process (``num_env_runners=0``,
    ``num_learners=0``: a laptop or a 2-core CI runner has no cores to spare)."""
    register_env(ENV, make_env)
    env_config = {"seconds": seconds, "critic": critic}
    if critic == "central":
        own_size = make_env({**env_config, "critic": "own"}).observation_space["follower_1"]
        module = RLModuleSpec(
            module_class=CentralCriticModule,
            model_config={"own_size": own_size.shape[0], "hidden": HIDDEN},
        )
    else:
        module = RLModuleSpec(model_config={"fcnet_hiddens": HIDDEN})
    return (
        PPOConfig()
        .environment(ENV, env_config=env_config)
        .env_runners(num_env_runners=0, num_envs_per_env_runner=1, rollout_fragment_length=batch)
        .learners(num_learners=0)
        .multi_agent(policies={POLICY}, policy_mapping_fn=lambda agent_id, *a, **k: POLICY)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={POLICY: module}))
        .training(train_batch_size_per_learner=batch, minibatch_size=batch // 2, num_epochs=2)
        .debugging(seed=seed)
    )


def probe_observation(algo: Algorithm, seed: int = 7) -> np.ndarray:
    """follower_1's first observation of a seeded episode of the algorithm's env (the same
    for every run): where greedy actions are compared."""
    obs, _ = make_env({**algo.config.env_config, "seconds": 1.0}).reset(seed=seed)
    return np.asarray(obs["follower_1"], dtype=np.float32)


def greedy_action(algo: Algorithm, obs: np.ndarray) -> np.ndarray:
    """The shared policy's deterministic action (normalized, [speed, heading] residual) for
    one observation: the mean of its Gaussian."""
    module = algo.get_module(POLICY)
    with torch.no_grad():
        out = module.forward_inference({Columns.OBS: torch.as_tensor(obs[None])})
    dist = module.get_inference_action_dist_cls().from_logits(out[Columns.ACTION_DIST_INPUTS])
    return dist.to_deterministic().sample()[0].numpy()


def train(algo: Algorithm, iterations: int) -> None:
    """``iterations`` PPO iterations, one line each: iteration, env steps so far, mean
    episode return (nan until an episode has ended)."""
    for _ in range(iterations):
        result = algo.train()
        runners = result[ENV_RUNNER_RESULTS]
        steps = int(runners[NUM_ENV_STEPS_SAMPLED_LIFETIME])
        ret = float(runners.get(EPISODE_RETURN_MEAN, math.nan))
        print(f"iteration {result['training_iteration']} env_steps {steps} return {ret:.3f}")


def describe(algo: Algorithm) -> str:
    """One line on what is trained: the policy's observation size (the layout's plus the
    features plug-in's; with a central critic, times the followers), the critic, the
    reward plug-in."""
    size = algo.get_module(POLICY).observation_space.shape[0]
    critic = algo.config.env_config["critic"]
    return f"policy {POLICY} obs {size} critic {critic} reward {REWARD.split('/')[-1]}"


def show(word: str, action: np.ndarray) -> None:
    """Print a greedy action in full precision (a restored policy must give the same)."""
    print(word, "greedy", *(repr(float(v)) for v in action))


def check_actor_is_local(algo: Algorithm) -> None:
    """With a central critic: the greedy action must not change when the other followers'
    part of the observation does (the actor runs on the follower's own observation)."""
    obs = probe_observation(algo)
    own = algo.get_module(POLICY).own_size
    noisy = obs.copy()
    noisy[own:] = np.random.default_rng(0).normal(size=obs.size - own)
    same = np.array_equal(greedy_action(algo, obs), greedy_action(algo, noisy))
    print(f"actor reads own {own} of {obs.size}: {'yes' if same else 'NO'}")


def main(
    iterations: int,
    batch: int,
    seconds: float,
    critic: str,
    out: Path,
    restore: Path | None,
    seed: int,
) -> None:
    # A fresh local Ray in a private folder: never one already running on this machine.
    with tempfile.TemporaryDirectory(prefix="ray") as ray_dir:
        ray.init(
            address="local",
            num_cpus=1,
            include_dashboard=False,
            log_to_driver=False,
            logging_level="warning",
            _node_ip_address="127.0.0.1",
            object_store_memory=80 * 1024 * 1024,
            _temp_dir=ray_dir,
        )
        try:
            register_env(ENV, make_env)  # the checkpoint names the env by this name
            if restore is None:
                algo = build_config(batch, seconds, critic, seed).build_algo()
            else:
                algo = Algorithm.from_checkpoint(str(restore.resolve()))
                show("restored", greedy_action(algo, probe_observation(algo)))
            try:
                print(describe(algo))
                train(algo, iterations)
                if algo.config.env_config["critic"] == "central":
                    check_actor_is_local(algo)
                if restore is None:
                    algo.save_to_path(str((out / "checkpoint").resolve()))
                    show("saved", greedy_action(algo, probe_observation(algo)))
                    print(f"wrote {out / 'checkpoint'}")
            finally:
                algo.stop()
        finally:
            ray.shutdown()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--batch", type=int, default=400, help="env steps per iteration")
    parser.add_argument("--seconds", type=float, default=10.0, help="episode length, s")
    parser.add_argument("--critic", choices=("own", "central"), default="own")
    parser.add_argument("--out", type=Path, default=Path("runs/rllib-example"))
    parser.add_argument("--restore", type=Path, help="a checkpoint to continue from")
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()
    main(a.iterations, a.batch, a.seconds, a.critic, a.out, a.restore, a.seed)
