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

    python examples/train_rllib.py [--iterations 3] [--batch 400] [--out runs/rllib-example]
    python examples/train_rllib.py --restore runs/rllib-example/checkpoint --iterations 1

It prints one line per iteration (``iteration 2 env_steps 800 return 98.8``: env steps so
far, the mean return of the episodes that ended in it, summed over the followers), the
shared policy's greedy action on a fixed observation after saving, and the same line after
restoring, so the two can be compared. Ray runs in this process only: no extra env-runner
or learner processes, no dashboard, on 127.0.0.1, stopped on the way out.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).resolve().parent
REWARD = f"{EXAMPLES / 'my_reward.py'}:Smooth?weight=0.2"
FEATURES = f"{EXAMPLES / 'my_features.py'}:GapRatio"
POLICY = "shared"
ENV = "openconvoy-randomized"


def make_env(env_config: dict):
    """The convoy env as RLlib wants it: ``RandomizedConvoyEnv`` (two followers, the
    plug-ins above, episodes of ``env_config["seconds"]`` s) in RLlib's
    ``ParallelPettingZooEnv``."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from openconvoy.train.randomization import EnvSpec, Randomization, RandomizedConvoyEnv

    spec = EnvSpec(
        n_followers=2, reward_fn=REWARD, obs_features=FEATURES, max_time_s=env_config["seconds"]
    )
    return ParallelPettingZooEnv(RandomizedConvoyEnv(spec, Randomization()))


def build_config(batch: int, seconds: float, seed: int):
    """PPO on the new API stack: one policy for every follower, ``batch`` env steps per
    iteration, sampling and learning in this process (``num_env_runners=0``,
    ``num_learners=0``: a laptop or a 2-core CI runner has no cores to spare)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.tune.registry import register_env

    register_env(ENV, make_env)
    return (
        PPOConfig()
        .environment(ENV, env_config={"seconds": seconds})
        .env_runners(num_env_runners=0, num_envs_per_env_runner=1, rollout_fragment_length=batch)
        .learners(num_learners=0)
        .multi_agent(policies={POLICY}, policy_mapping_fn=lambda agent_id, *a, **k: POLICY)
        .rl_module(
            rl_module_spec=MultiRLModuleSpec(
                rl_module_specs={POLICY: RLModuleSpec(model_config={"fcnet_hiddens": [64, 64]})}
            )
        )
        .training(train_batch_size_per_learner=batch, minibatch_size=batch // 2, num_epochs=2)
        .debugging(seed=seed)
    )


def probe_observation(seed: int = 7) -> np.ndarray:
    """follower_1's first observation of a seeded episode (the same for every run): where
    greedy actions are compared."""
    obs, _ = make_env({"seconds": 1.0}).reset(seed=seed)
    return np.asarray(obs["follower_1"], dtype=np.float32)


def greedy_action(algo, obs: np.ndarray) -> np.ndarray:
    """The shared policy's deterministic action (normalized, [speed, heading] residual) for
    one observation: the mean of its Gaussian."""
    import torch

    module = algo.get_module(POLICY)
    with torch.no_grad():
        out = module.forward_inference({"obs": torch.as_tensor(obs[None])})
    dist = module.get_inference_action_dist_cls().from_logits(out["action_dist_inputs"])
    return dist.to_deterministic().sample()[0].numpy()


def train(algo, iterations: int) -> None:
    """``iterations`` PPO iterations, one line each: iteration, env steps so far, mean
    episode return (nan until an episode has ended)."""
    from ray.rllib.utils.metrics import (
        ENV_RUNNER_RESULTS,
        EPISODE_RETURN_MEAN,
        NUM_ENV_STEPS_SAMPLED_LIFETIME,
    )

    for _ in range(iterations):
        result = algo.train()
        runners = result[ENV_RUNNER_RESULTS]
        steps = int(runners[NUM_ENV_STEPS_SAMPLED_LIFETIME])
        ret = float(runners.get(EPISODE_RETURN_MEAN, math.nan))
        print(f"iteration {result['training_iteration']} env_steps {steps} return {ret:.3f}")


def describe(algo) -> str:
    """One line on what is trained: the agents, the policy's observation size (the
    layout's plus the features plug-in's), the reward plug-in."""
    size = algo.get_module(POLICY).observation_space.shape[0]
    return f"policy {POLICY} obs {size} reward {REWARD.split('/')[-1]}"


def show(word: str, action: np.ndarray) -> None:
    """Print a greedy action in full precision (a restored policy must give the same)."""
    print(word, "greedy", *(repr(float(v)) for v in action))


def main(
    iterations: int, batch: int, seconds: float, out: Path, restore: Path | None, seed: int
) -> None:
    import ray

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
            config = build_config(batch, seconds, seed)  # also registers the env
            if restore is None:
                algo = config.build_algo()
            else:
                from ray.rllib.algorithms.algorithm import Algorithm

                algo = Algorithm.from_checkpoint(str(restore.resolve()))
                show("restored", greedy_action(algo, probe_observation()))
            try:
                print(describe(algo))
                train(algo, iterations)
                if restore is None:
                    algo.save_to_path(str((out / "checkpoint").resolve()))
                    show("saved", greedy_action(algo, probe_observation()))
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
    parser.add_argument("--out", type=Path, default=Path("runs/rllib-example"))
    parser.add_argument("--restore", type=Path, help="a checkpoint to continue from")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.iterations, args.batch, args.seconds, args.out, args.restore, args.seed)
