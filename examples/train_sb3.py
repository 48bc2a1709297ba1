"""Train a follower with stable-baselines3 from Python, then evaluate it beside the paper's
controller (needs the ``train`` extra).

``OpenConvoy-v0`` is the single-agent Gymnasium view of ``ConvoyEnv``: the learner drives
``follower_1`` and the other follower runs the paper's controller. Any Gymnasium learner
works on it; ``openconvoy train`` is the full recipe (parameter sharing, the batched
simulator, randomization, validation). A few thousand steps learn little: raise ``--steps``
for a policy worth keeping.

    python examples/train_sb3.py [--steps 2048] [--out runs/sb3-example]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium
import numpy as np
from stable_baselines3 import PPO

import openconvoy.envs  # noqa: F401  (registers OpenConvoy-v0)


def evaluate(act, seed: int = 100, per: float = 0.2) -> float:
    """p95 of follower_1's platooning error over one paper episode at ``per``."""
    from openconvoy.comms.loss import LossConfig

    env = gymnasium.make("OpenConvoy-v0", loss=LossConfig(per=per))
    obs, info = env.reset(seed=seed)
    errors, done = [], False
    while not done:
        obs, _, terminated, truncated, info = env.step(act(obs))
        done = terminated or truncated
        if info["platooning_error_m"] is not None:
            errors.append(info["platooning_error_m"])
    env.close()
    return float(np.percentile(errors, 95))


def main(steps: int, out: Path, seed: int = 0) -> dict[str, float]:
    env = gymnasium.make("OpenConvoy-v0")
    model = PPO("MlpPolicy", env, n_steps=512, batch_size=128, seed=seed, verbose=0)
    model.learn(total_timesteps=steps)
    out.mkdir(parents=True, exist_ok=True)
    model.save(out / "ppo_follower.zip")

    from openconvoy.policies.spec import load_policy

    paper = load_policy("paper")
    paper.reset(seed)
    return {
        "trained_p95_m": evaluate(lambda obs: model.predict(obs, deterministic=True)[0]),
        "paper_p95_m": evaluate(paper.act),
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=Path("runs/sb3-example"))
    args = parser.parse_args()
    for key, value in main(args.steps, args.out).items():
        print(f"{key:<16}{value:.3f}")
    print(f"wrote {args.out / 'ppo_follower.zip'}")
