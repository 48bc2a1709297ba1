"""``openconvoy train``: PPO or SAC with one policy shared by all followers.

A run directory holds::

    config.toml        the resolved TrainConfig (``openconvoy train --config`` reads it)
    policy.zip         the run's policy: the SB3 model with OpenConvoy metadata inside
                       (layout, member config, control rate, observation normalization,
                       action scaling, residual base): ``--policy RUN/policy.zip`` works
                       everywhere. With validation (default), the best-validated of the
                       checkpoints and the final network; else the final network
    last.zip           the final network (with validation)
    validation.json    every validated file's objective and runs, and which was chosen
    policy.json        policy.zip's metadata, readable
    vecnormalize.pkl   SB3's VecNormalize at the end (pairs with the final network, to
                       resume training; every .zip carries its own statistics)
    checkpoints/       policy_<steps>_steps.zip, each loadable like policy.zip
    tb/                TensorBoard event files (rollout/ep_rew_mean, rollout/platooning_error_m, ...)
    train.json         steps, wall time (of learning), steps per second, whether the
                       wall-clock budget stopped learning, the PER curriculum's steps

``openconvoy export RUN_DIR --out policy.npz`` turns it into the numpy-only artifact.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.running_mean_std import RunningMeanStd
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from openconvoy.core.errors import ConfigError
from openconvoy.policies.learned import LearnedMeta, read_zip_meta, write_zip_meta
from openconvoy.train.config import TrainConfig, dumps_train_config
from openconvoy.train.randomization import RandomizedConvoyEnv
from openconvoy.train.schedule import RunClock, Schedule, linear_schedule
from openconvoy.train.validate import Validation, validate
from openconvoy.train.vecenv.randomized import RandomizedVectorVecEnv, batched_refusal
from openconvoy.train.vecenv.shared import shared_policy_vec_env

POLICY_FILE = "policy.zip"
LAST_FILE = "last.zip"
VECNORM_FILE = "vecnormalize.pkl"


@dataclass(frozen=True)
class TrainResult:
    """What a finished run reports."""

    run_dir: Path
    policy_path: Path
    steps: int
    wall_s: float
    stopped_by_budget: bool = False
    validation: Validation | None = None
    """The chosen policy's validation (None without validation seeds)."""
    base_validation: Validation | None = None
    """Its reference on the same grid: the residual's base, or ``paper`` from scratch."""

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.wall_s if self.wall_s > 0 else math.nan


def make_vec_env(config: TrainConfig) -> VecEnv:
    """The training VecEnv: parameter-sharing slots, episode statistics, VecNormalize."""
    venv: VecEnv = VecMonitor(simulator_vec_env(config))
    if config.normalize_obs or config.normalize_reward:
        gamma = config.ppo.gamma if config.algo == "ppo" else config.sac.gamma
        venv = VecNormalize(
            venv, norm_obs=config.normalize_obs, norm_reward=config.normalize_reward, gamma=gamma
        )
    return venv


def simulator_vec_env(config: TrainConfig) -> VecEnv:
    """The randomized convoys, one slot per follower: batched (``train.vecenv.randomized``) unless
    ``config.vec_env`` says ``supersuit`` or, with ``auto``, the batched simulator refuses
    the configuration (one line on stderr says why)."""
    if config.vec_env != "supersuit":
        why = batched_refusal(config.env, config.randomization)
        if why is None:
            return RandomizedVectorVecEnv(
                config.env, config.randomization, config.n_envs, config.n_worlds
            )
        if config.vec_env == "batched":
            raise ConfigError(f"vec_env = batched: {why}")
        print(
            f"openconvoy train: the batched simulator cannot run this configuration ({why}); "
            "training on SuperSuit's per-convoy path",
            file=sys.stderr,
        )
    return shared_policy_vec_env(
        lambda: RandomizedConvoyEnv(config.env, config.randomization), config.n_envs
    )


def _activation(name: str):
    import torch.nn as nn

    return {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}[name]


def make_model(
    config: TrainConfig,
    venv: VecEnv,
    tensorboard_dir: Path | None,
    clock: RunClock | None = None,
) -> BaseAlgorithm:
    """The SB3 model for ``config`` on ``venv`` (CPU); ``clock``: the run's progress
    (a linear learning rate follows it; default: steps only)."""
    tb = None if tensorboard_dir is None else str(tensorboard_dir)
    if config.algo == "ppo":
        p = config.ppo
        # Keep a minibatch within one rollout: SB3 warns (and wastes data) otherwise.
        batch = min(p.batch_size, p.n_steps * venv.num_envs)
        clock = clock or RunClock(config.total_steps, None)
        lr = p.learning_rate
        return PPO(
            "MlpPolicy",
            venv,
            n_steps=p.n_steps,
            batch_size=batch,
            n_epochs=p.n_epochs,
            learning_rate=linear_schedule(lr, clock) if p.lr_schedule == "linear" else lr,
            gamma=p.gamma,
            gae_lambda=p.gae_lambda,
            clip_range=p.clip_range,
            ent_coef=p.ent_coef,
            max_grad_norm=p.max_grad_norm,
            use_sde=bool(p.use_sde),
            sde_sample_freq=p.sde_sample_freq,
            policy_kwargs={
                "net_arch": {"pi": list(p.net_arch), "vf": list(p.net_arch)},
                "activation_fn": _activation(p.activation),
                "log_std_init": p.log_std_init,
            },
            seed=config.seed,
            device="cpu",
            tensorboard_log=tb,
            verbose=0,
        )
    s = config.sac
    return SAC(
        "MlpPolicy",
        venv,
        learning_rate=s.learning_rate,
        buffer_size=s.buffer_size,
        learning_starts=s.learning_starts,
        batch_size=s.batch_size,
        tau=s.tau,
        gamma=s.gamma,
        train_freq=s.train_freq,
        gradient_steps=s.gradient_steps,
        policy_kwargs={"net_arch": list(s.net_arch), "activation_fn": _activation(s.activation)},
        seed=config.seed,
        device="cpu",
        tensorboard_log=tb,
        verbose=0,
    )


def policy_meta(config: TrainConfig, venv: VecEnv, steps: int) -> LearnedMeta:
    """The metadata recorded with the policy: layout, member config, rate, normalization."""
    mean = var = None
    clip, eps = 10.0, 1e-8
    if isinstance(venv, VecNormalize) and venv.norm_obs:
        rms = venv.obs_rms
        assert isinstance(rms, RunningMeanStd)  # a Box observation space: one statistic
        mean, var = np.array(rms.mean, dtype=np.float64), np.array(rms.var, dtype=np.float64)
        clip, eps = float(venv.clip_obs), float(venv.epsilon)
    spec = config.env
    return LearnedMeta(
        algo=config.algo,
        layout=spec.member_config.layout.describe(),
        member_config=spec.member_config,
        control_rate_hz=spec.rate_hz,
        action_low=spec.bounds[0],
        action_high=spec.bounds[1],
        base=spec.base_config(),
        base_plugin=spec.plugin_base,
        obs_features=spec.obs_features,
        feature_size=spec.make_features()[1],
        residual_scale=spec.residual_scale if spec.base_policy else (0.0, 0.0),
        obs_mean=mean,
        obs_var=var,
        obs_clip=clip,
        obs_epsilon=eps,
        name=config.name,
        extra={"steps": int(steps), "seed": config.seed},
    )


def save_policy(model: BaseAlgorithm, config: TrainConfig, path: Path) -> Path:
    """Save ``model`` to ``path`` (.zip) with OpenConvoy's metadata inside."""
    model.save(str(path))
    venv = model.get_env()
    assert venv is not None
    write_zip_meta(path, policy_meta(config, venv, model.num_timesteps))
    return path


class _Progress(BaseCallback):
    """A tqdm progress bar over agent steps (SB3's own needs ``rich``, which we don't)."""

    def __init__(self, total: int, enabled: bool) -> None:
        super().__init__()
        self.total = total
        self.enabled = enabled
        self._bar = None

    def _on_training_start(self) -> None:
        if self.enabled:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit="step", unit_scale=True, desc="train")

    def _on_step(self) -> bool:
        if self._bar is not None:
            self._bar.update(self.training_env.num_envs)
        return True

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()


class _ConvoyStats(BaseCallback):
    """Logs what matters for a follower to TensorBoard: mean platooning error (m) and
    collisions per rollout (from the environments' infos)."""

    def __init__(self) -> None:
        super().__init__()
        self._err_sum = 0.0
        self._n = 0
        self._collisions = 0

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", ()):
            err = info.get("platooning_error_m")
            if err is not None and math.isfinite(err):
                self._err_sum += err
                self._n += 1
            self._collisions += bool(info.get("collision", False))
        return True

    def _on_rollout_end(self) -> None:
        if self._n:
            self.logger.record("rollout/platooning_error_m", self._err_sum / self._n)
        self.logger.record("rollout/collisions", self._collisions)
        self._err_sum, self._n, self._collisions = 0.0, 0, 0


def _validate(config: TrainConfig, path: Path | str, steps: int) -> Validation:
    return validate(
        path,
        config.validation_pers,
        config.validation_seeds,
        steps,
        duration_s=config.validation_duration_s,
    )


class _Checkpoint(BaseCallback):
    """Every ``every`` agent steps, a loadable ``policy_<steps>_steps.zip``, validated
    when the config asks (``validations`` collects the results)."""

    def __init__(self, config: TrainConfig, directory: Path, every: int, clock: RunClock) -> None:
        super().__init__()
        self.config = config
        self.directory = directory
        self.every = every
        self.clock = clock
        self._next = every
        self.validations: list[Validation] = []

    def _on_step(self) -> bool:
        if self.every and self.num_timesteps >= self._next:
            start = time.perf_counter()
            self.directory.mkdir(parents=True, exist_ok=True)
            path = save_policy(
                self.model, self.config, self.directory / f"policy_{self.num_timesteps}_steps.zip"
            )
            if self.config.validation_seeds:
                self.validations.append(_validate(self.config, path, self.num_timesteps))
                self.logger.record("validation/objective", self.validations[-1].objective)
            self.clock.timed_validation(time.perf_counter() - start)
            self._next += self.every
        return True


def train(
    config: TrainConfig,
    run_dir: str | Path,
    progress_bar: bool = True,
    overwrite: bool = False,
) -> TrainResult:
    """Train ``config`` into ``run_dir`` (see the module docstring for its files)."""
    import torch

    run_dir = Path(run_dir)
    if (run_dir / POLICY_FILE).exists() and not overwrite:
        raise ConfigError(f"{run_dir} already holds a trained policy; choose another --out")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.toml").write_text(dumps_train_config(config), encoding="utf-8")
    torch.set_num_threads(config.torch_threads)

    clock = RunClock(config.total_steps, config.budget_s, validates=bool(config.validation_seeds))
    venv = make_vec_env(config)
    model = make_model(config, venv, run_dir / "tb", clock)
    checkpoints = _Checkpoint(config, run_dir / "checkpoints", config.checkpoint_every, clock)
    schedule = Schedule(clock, config.randomization.per_range, config.per_curriculum)
    callbacks = CallbackList(
        [_Progress(config.total_steps, progress_bar), _ConvoyStats(), checkpoints, schedule]
    )
    schedule.prime(venv)
    start = time.perf_counter()
    model.learn(total_timesteps=config.total_steps, callback=callbacks, tb_log_name=config.algo)
    wall = time.perf_counter() - start
    if schedule.stopped_by_clock and not getattr(model, "_n_updates", 1):
        venv.close()
        raise ConfigError(
            f"the wall-clock budget of {config.budget_s:g} s stopped learning after "
            f"{model.num_timesteps} agent steps, before the network's first update "
            f"({_first_update(config, venv.num_envs)} steps): nothing was learned; give a "
            "larger --budget, or none (total_steps alone)"
        )

    policy, chosen, base = _choose_policy(model, config, run_dir, checkpoints.validations)
    if isinstance(venv, VecNormalize):
        venv.save(str(run_dir / VECNORM_FILE))
    meta = read_zip_meta(policy)
    (run_dir / "policy.json").write_text(json.dumps(meta.to_json(), indent=1), encoding="utf-8")
    result = TrainResult(
        run_dir, policy, int(model.num_timesteps), wall, schedule.stopped_by_clock, chosen, base
    )
    _write_summary(config, result, run_dir / "train.json", schedule.per_high)
    venv.close()
    return result


def _first_update(config: TrainConfig, slots: int) -> int:
    """Agent steps before the network is first updated: one PPO rollout of every slot,
    or SAC's ``learning_starts``."""
    return config.ppo.n_steps * slots if config.algo == "ppo" else config.sac.learning_starts


def _choose_policy(
    model: BaseAlgorithm, config: TrainConfig, run_dir: Path, validations: list[Validation]
) -> tuple[Path, Validation | None, Validation | None]:
    """Write ``policy.zip``: the best-validated of the checkpoints and the final network
    (``last.zip``), with ``validation.json`` (which also validates the reference: the
    residual's base, or ``paper`` for a policy from scratch); without validation, the
    final network. Returns the file, its validation and the reference's."""
    policy = run_dir / POLICY_FILE
    if not config.validation_seeds:
        return save_policy(model, config, policy), None, None
    last = save_policy(model, config, run_dir / LAST_FILE)
    validations = [*validations, _validate(config, last, model.num_timesteps)]
    # The earliest of equally good files wins (min keeps the first).
    best = min(validations, key=lambda v: v.objective)
    shutil.copyfile(best.path, policy)
    base = _validate(config, config.env.base_policy or REFERENCE_POLICY, 0)
    report = {
        "pers": list(config.validation_pers),
        "seeds": list(config.validation_seeds),
        "chosen": best.path,
        "chosen_steps": best.steps,
        "validations": [v.to_json() for v in validations],
        "base": base.to_json(),
    }
    (run_dir / "validation.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    return policy, best, base


REFERENCE_POLICY = "paper"
"""What a policy learned from scratch is validated beside: the paper's controller."""


def _write_summary(
    config: TrainConfig, result: TrainResult, path: Path, per_high: list[tuple[int, float]]
) -> None:
    summary: dict[str, Any] = {
        "algo": config.algo,
        "steps": result.steps,
        "stopped_by_budget": result.stopped_by_budget,
        "budget_s": config.budget_s,
        "per_high": [[steps, round(v, 4)] for steps, v in per_high],
        "wall_s": round(result.wall_s, 3),
        "steps_per_s": round(result.steps_per_s, 1),
        "torch_threads": config.torch_threads,
        "n_slots": config.n_slots,
    }
    path.write_text(json.dumps(summary, indent=1), encoding="utf-8")
