"""The training configuration: typed, strict, TOML round-trip (``config.toml`` of a run).

``TrainConfig`` holds everything that determines a run: algorithm and its
hyperparameters, step budget, vectorization, seed, the environment (``EnvSpec``: convoy
size, member configuration and thus observation layout, control rate, action scaling,
reward) and the domain randomization. ``openconvoy train --config FILE`` reads a TOML file
with these keys (unknown keys are errors naming the key); the run directory keeps the
resolved config so a run can be repeated.

The defaults are sized for a 2-core machine: a working follower in under 15 minutes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from openconvoy.core.config import Range, dumps_toml, from_dict, load_toml, to_dict
from openconvoy.core.errors import ConfigError
from openconvoy.train.randomization import EnvSpec, Randomization

ALGOS = ("ppo", "sac")
VEC_ENVS = ("auto", "batched", "supersuit")
ACTIVATION_NAMES = ("tanh", "relu", "elu", "leaky_relu")


@dataclass(frozen=True)
class PPOConfig:
    """stable-baselines3 PPO hyperparameters (see its documentation). ``n_steps`` is per
    VecEnv slot; ``lr_schedule`` ``linear`` decays ``learning_rate`` to 0 over the run
    (late updates then refine instead of swinging the policy), ``constant`` keeps it;
    ``log_std_init`` is the initial log standard deviation of the normalized
    actions (-1: std 0.37, enough to explore, not so much that a car swerves off the road);
    ``use_sde``: generalized state-dependent exploration (noise that changes every
    ``sde_sample_freq`` steps, -1: once per rollout, instead of white noise every tick);
    None: on learning from scratch (``TrainConfig`` resolves it from the base), where a
    white-noise speed setpoint at 20 Hz is filtered away by the vehicle's lag and teaches
    nothing, off for residual policies."""

    n_steps: Annotated[int, Range(1, 10000000)] = 64
    batch_size: Annotated[int, Range(1, 10000000)] = 512
    n_epochs: Annotated[int, Range(1, 1000)] = 5
    learning_rate: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 3e-4
    lr_schedule: str = "linear"
    gamma: Annotated[float, Range(0.0, 1.0)] = 0.98
    gae_lambda: Annotated[float, Range(0.0, 1.0)] = 0.95
    clip_range: Annotated[float, Range(0.0, 10.0, lo_open=True)] = 0.2
    ent_coef: Annotated[float, Range(0.0, 10.0)] = 0.0
    max_grad_norm: Annotated[float, Range(0.0, 1000.0, lo_open=True)] = 0.5
    net_arch: tuple[Annotated[int, Range(1, 100_000)], ...] = (64, 64)
    activation: str = "tanh"
    log_std_init: Annotated[float, Range(-20.0, 5.0)] = -1.0
    use_sde: bool | None = None
    sde_sample_freq: Annotated[int, Range(-1, 1000000)] = 8

    def __post_init__(self) -> None:
        object.__setattr__(self, "net_arch", tuple(int(n) for n in self.net_arch))
        if self.activation not in ACTIVATION_NAMES:
            raise ConfigError(
                f"ppo.activation: unknown {self.activation!r}; expected one of {', '.join(ACTIVATION_NAMES)}"
            )
        if self.lr_schedule not in ("linear", "constant"):
            raise ConfigError(
                f"ppo.lr_schedule: unknown {self.lr_schedule!r}; expected linear or constant"
            )
        if self.n_steps < 2 or self.batch_size < 2 or self.n_epochs < 1:
            raise ConfigError("ppo: n_steps and batch_size must be >= 2, n_epochs >= 1")


@dataclass(frozen=True)
class SACConfig:
    """stable-baselines3 SAC hyperparameters (see its documentation)."""

    learning_rate: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 3e-4
    buffer_size: Annotated[int, Range(1, 1000000000)] = 300_000
    learning_starts: Annotated[int, Range(0, 1000000000)] = 5_000
    batch_size: Annotated[int, Range(1, 10000000)] = 256
    tau: Annotated[float, Range(0.0, 1.0, lo_open=True)] = 0.005
    gamma: Annotated[float, Range(0.0, 1.0)] = 0.98
    train_freq: Annotated[int, Range(1, 1000000)] = 1
    gradient_steps: Annotated[int, Range(-1, 1000000)] = 1
    net_arch: tuple[Annotated[int, Range(1, 100_000)], ...] = (256, 256)
    activation: str = "relu"

    def __post_init__(self) -> None:
        object.__setattr__(self, "net_arch", tuple(int(n) for n in self.net_arch))
        if self.activation not in ACTIVATION_NAMES:
            raise ConfigError(
                f"sac.activation: unknown {self.activation!r}; expected one of {', '.join(ACTIVATION_NAMES)}"
            )


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        algo: ``ppo`` or ``sac``.
        total_steps: agent steps (every follower's step counts: parameter sharing).
        n_envs: environments stepped together; VecEnv slots = n_envs * env.n_followers.
        seed: seeds the networks, the sampling and the environments (env i: seed + i).
        env: the environment (convoy size, member config and layout, rate, actions, reward).
        randomization: what is redrawn every episode.
        normalize_obs, normalize_reward: VecNormalize (the observation statistics travel
            with the policy; reward normalization only helps the learner).
        checkpoint_every: agent steps between checkpoints (0: none). Each checkpoint is
            also validated when ``validation_seeds`` is not empty.
        validation_pers, validation_seeds: the validation grid: deterministic runs of the
            ``paper`` scenario, with seeds kept apart from those reports use (0..).
            ``policy.zip`` is the checkpoint (or final network) with the lowest validation
            objective (``openconvoy.train.tune.objective_of``: mean p95 platooning error,
            collisions heavily penalized, mean speed difference), as SB3's EvalCallback
            keeps a best model; ``last.zip`` is the final network. Empty seeds: no
            validation, ``policy.zip`` is the final network.
        validation_duration_s: length of the validation runs (None: the scenario's).
        budget_s: wall-clock budget of the whole run, seconds (None: none): learning
            stops when what is left is what the final validation and the run directory
            need (``train.schedule.RunClock``), and the learning rate and the curriculum
            follow the clock where it is further along than the steps.
        per_curriculum: the fraction of the run over which the training PER cap rises
            linearly from ``randomization.per_range[0]`` to ``per_range[1]`` (0: the
            whole range from the start; the batched simulator only).
        torch_threads: torch CPU threads (the environments run in this process too).
        name: the policy's label in logs and reports.
        vec_env: the simulator: ``batched`` (``envs.VectorConvoyEnv``, all convoys in
            arrays: ``train.vecenv.randomized``), ``supersuit`` (one ``ConvoyEnv`` per convoy through
            SuperSuit: ``train.vecenv.shared``), or ``auto``: batched unless the randomization asks
            for what it does not model (traffic), then
            SuperSuit, with one line on stderr saying so.
        n_worlds: batched: groups of convoys that share a drawn world (vehicles, burst
            model, latency); each convoy draws its own PER.
    """

    algo: str = "ppo"
    total_steps: Annotated[int, Range(1, 1000000000000)] = 600_000
    n_envs: Annotated[int, Range(1, 1024)] = 32
    seed: Annotated[int, Range(0, 4294967295)] = 0
    env: EnvSpec = field(default_factory=EnvSpec)
    randomization: Randomization = field(default_factory=Randomization)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    normalize_obs: bool = True
    normalize_reward: bool = True
    checkpoint_every: Annotated[int, Range(0, 1000000000000)] = 100_000
    validation_pers: tuple[Annotated[float, Range(0.0, 1.0)], ...] = (0.0, 0.3, 0.6)
    validation_seeds: tuple[Annotated[int, Range(0, 2**32 - 1)], ...] = (1000, 1001, 1002)
    validation_duration_s: Annotated[float, Range(0.0, 604800.0, lo_open=True)] | None = None
    budget_s: Annotated[float, Range(0.0, 604800.0, lo_open=True)] | None = None
    per_curriculum: Annotated[float, Range(0.0, 1.0)] = 0.0
    torch_threads: Annotated[int, Range(1, 1024)] = 1
    name: str = "learned"
    vec_env: str = "auto"
    n_worlds: Annotated[int, Range(1, 1024)] = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "validation_pers", tuple(float(p) for p in self.validation_pers))
        object.__setattr__(self, "validation_seeds", tuple(int(s) for s in self.validation_seeds))
        if self.validation_seeds and not self.validation_pers:
            raise ConfigError("validation_seeds need validation_pers")
        if self.ppo.use_sde is None:
            sde = not self.env.base_policy
            object.__setattr__(self, "ppo", dataclasses.replace(self.ppo, use_sde=sde))
        if self.vec_env not in VEC_ENVS:
            raise ConfigError(
                f"vec_env: unknown {self.vec_env!r}; expected one of {', '.join(VEC_ENVS)}"
            )
        if self.algo not in ALGOS:
            raise ConfigError(f"algo: unknown {self.algo!r}; expected one of {', '.join(ALGOS)}")
        if self.total_steps < 1 or self.n_envs < 1:
            raise ConfigError("total_steps and n_envs must be positive")
        if self.checkpoint_every < 0 or self.torch_threads < 1:
            raise ConfigError("checkpoint_every must be >= 0 and torch_threads >= 1")

    @property
    def n_slots(self) -> int:
        """VecEnv slots: one per follower per environment."""
        return self.n_envs * self.env.n_followers


SCRATCH_RUN: dict[str, Any] = {
    "total_steps": 6_000_000,
    "n_envs": 64,
    "n_worlds": 4,
    "checkpoint_every": 250_000,
    "per_curriculum": 0.0,
}
"""The run ``--base none`` brings (where the config holds the residual run's values):
64 convoys in 4 worlds, validated every 250k steps, learning for 6M agent steps. The
budget is in steps, not wall-clock time, so the same command and seed give the same
policy on any machine (``--budget`` adds a wall-clock limit where one is wanted)."""
SCRATCH_PPO: dict[str, Any] = {"n_steps": 32, "batch_size": 1024}
"""PPO settings ``--base none`` brings: 32-step rollouts of 128 slots, 4 minibatches."""


def run_defaults(residual: bool) -> tuple[dict[str, Any], dict[str, Any]]:
    """The defaults of a run's size and of PPO of each kind (residual or from scratch),
    over the keys the kinds differ in: ``(top-level, ppo)``."""
    if not residual:
        return SCRATCH_RUN, SCRATCH_PPO
    top = {f.name: f.default for f in dataclasses.fields(TrainConfig) if f.name in SCRATCH_RUN}
    ppo = {f.name: f.default for f in dataclasses.fields(PPOConfig) if f.name in SCRATCH_PPO}
    return top, ppo


def load_train_config(path: str | Path) -> TrainConfig:
    """A TrainConfig from a TOML file whose top-level keys are TrainConfig's."""
    return from_dict(TrainConfig, load_toml(path), str(path))


def dumps_train_config(config: TrainConfig) -> str:
    """TOML text that ``load_train_config`` reads back to ``config``."""
    return dumps_toml(to_dict(config))
