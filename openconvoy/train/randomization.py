"""Domain randomization: a ConvoyEnv whose world is redrawn at every episode.

What the real world varies and a policy must survive (issue 6): packet error rate
(uniform in ``per_range``), bursty loss (Gilbert-Elliott with a drawn mean burst length,
with probability ``burst_prob``), latency and jitter, GPS noise, the vehicles (drawn from a
pool of presets, fitted ``.toml`` presets included, with their autopilot response jittered)
and the scenario. ``RandomizedConvoyEnv`` is a PettingZoo ``ParallelEnv`` with a fixed set of
agents (``n_followers``), so SuperSuit can turn it into a parameter-sharing VecEnv.

Actions are normalized: each agent sends ``[-1, 1]^2``; ``EnvSpec`` says how it becomes
``[speed_mps, heading_change_rad]``, absolute or as a residual on a classical base policy
(``openconvoy.policies.learned.compose_action``, the function the deployed policy uses,
so a trained network means the same thing in both places).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Annotated, Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from openconvoy.comms.loss import LossConfig
from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError
from openconvoy.core.member import MemberConfig
from openconvoy.core.plugins import join_args
from openconvoy.envs.convoy_env import ConvoyEnv
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy
from openconvoy.policies.learned import compose_action
from openconvoy.policies.spec import classical_config, plugin_of
from openconvoy.train.shaping import Shaping

PLANT_JITTER_FIELDS = (
    "speed_lag_s",
    "accel_max_mps2",
    "decel_max_mps2",
    "turn_rate_max_radps",
    "heading_lag_s",
    "actuation_delay_s",
)
"""Autopilot-response fields of a vehicle preset scaled by ``1 + U(-plant_jitter, +plant_jitter)``."""


@dataclass(frozen=True)
class Randomization:
    """Ranges drawn at every episode start (SI units; a range ``(a, a)`` is fixed).

    Attributes:
        scenarios: scenario specs drawn uniformly (all must fit ``n_followers``). Default
            ``paper`` only: on the oval the reward's straight-line gap and the path gap the
            controllers keep disagree in the bends, which blurs what the learner is paid for.
        per_range: packet error rate, uniform.
        burst_prob: probability that an episode's links lose packets in Gilbert-Elliott
            bursts instead of independently (same long-run PER).
        mean_burst_s_range: mean burst length when bursty, seconds, uniform.
        latency_s_range: base delivery delay, seconds, uniform.
        jitter_s_range: extra uniform delay jitter bound, seconds, uniform.
        gps_noise_m_range: position noise standard deviation per axis, metres, uniform.
            Jitter and GPS noise are off by default.
        vehicles: preset names or fitted-preset ``.toml`` paths; each vehicle (leader
            included) is drawn from them. Empty: the scenario's own vehicles.
        plant_jitter: relative jitter of each drawn vehicle's autopilot response
            (``PLANT_JITTER_FIELDS``); 0.2 = ±20 %.
    """

    scenarios: tuple[str, ...] = ("paper",)
    per_range: tuple[Annotated[float, Range(0.0, 1.0)], Annotated[float, Range(0.0, 1.0)]] = (
        0.0,
        0.6,
    )
    burst_prob: Annotated[float, Range(0.0, 1.0)] = 0.3
    mean_burst_s_range: tuple[
        Annotated[float, Range(0.0, 3600.0)], Annotated[float, Range(0.0, 3600.0)]
    ] = (0.2, 1.0)
    latency_s_range: tuple[
        Annotated[float, Range(0.0, 60.0)], Annotated[float, Range(0.0, 60.0)]
    ] = (0.0, 0.05)
    jitter_s_range: tuple[
        Annotated[float, Range(0.0, 60.0)], Annotated[float, Range(0.0, 60.0)]
    ] = (0.0, 0.0)
    gps_noise_m_range: tuple[
        Annotated[float, Range(0.0, 1000.0)], Annotated[float, Range(0.0, 1000.0)]
    ] = (0.0, 0.0)
    vehicles: tuple[str, ...] = ("1/10", "1/6")
    plant_jitter: Annotated[float, Range(0.0, 0.9)] = 0.2

    def __post_init__(self) -> None:
        for name in (
            "scenarios",
            "vehicles",
            "per_range",
            "mean_burst_s_range",
            "latency_s_range",
            "jitter_s_range",
            "gps_noise_m_range",
        ):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if not self.scenarios:
            raise ConfigError("randomization.scenarios: give at least one scenario")
        for name in (
            "per_range",
            "mean_burst_s_range",
            "latency_s_range",
            "jitter_s_range",
            "gps_noise_m_range",
        ):
            lo, hi = _pair(getattr(self, name), f"randomization.{name}")
            if lo < 0 or hi < lo:
                raise ConfigError(f"randomization.{name}: need 0 <= low <= high, got ({lo}, {hi})")
        if self.per_range[1] > 0.95:
            raise ConfigError(
                f"randomization.per_range: PER above 0.95 leaves nothing to learn from, got {self.per_range[1]}"
            )
        if self.mean_burst_s_range[0] <= 0:
            raise ConfigError("randomization.mean_burst_s_range: bursts must be longer than 0 s")
        if not 0.0 <= self.burst_prob <= 1.0:
            raise ConfigError(f"randomization.burst_prob must be in [0, 1], got {self.burst_prob}")
        if not 0.0 <= self.plant_jitter < 1.0:
            raise ConfigError(
                f"randomization.plant_jitter must be in [0, 1), got {self.plant_jitter}"
            )
        for v in self.vehicles:
            vehicle_preset(v)  # an unknown preset or missing file fails now, not mid-training


def _pair(value: tuple[float, ...], where: str) -> tuple[float, float]:
    if len(value) != 2:
        raise ConfigError(f"{where}: expected [low, high], got {list(value)}")
    return float(value[0]), float(value[1])


@dataclass(frozen=True)
class EpisodeWorld:
    """One draw of ``Randomization``: what an episode runs in."""

    scenario: str
    loss: LossConfig
    gps_noise_m: float
    vehicles: tuple[VehiclePreset, ...] | None


def draw_world(r: Randomization, n_followers: int, rng: np.random.Generator) -> EpisodeWorld:
    """Draw one episode's world from ``r`` with ``rng``."""
    scenario = r.scenarios[int(rng.integers(len(r.scenarios)))]
    per = float(rng.uniform(*r.per_range))
    bursty = per > 0.0 and rng.random() < r.burst_prob
    loss = LossConfig(
        per=per,
        model="gilbert-elliott" if bursty else "bernoulli",
        mean_burst_s=float(rng.uniform(*r.mean_burst_s_range)),
        latency_s=float(rng.uniform(*r.latency_s_range)),
        jitter_s=float(rng.uniform(*r.jitter_s_range)),
    )
    vehicles = None
    if r.vehicles:
        pool = [vehicle_preset(v) for v in r.vehicles]
        vehicles = tuple(
            _jitter(pool[int(rng.integers(len(pool)))], r.plant_jitter, rng)
            for _ in range(n_followers + 1)
        )
    return EpisodeWorld(scenario, loss, float(rng.uniform(*r.gps_noise_m_range)), vehicles)


def _jitter(preset: VehiclePreset, amount: float, rng: np.random.Generator) -> VehiclePreset:
    if amount <= 0.0:
        return preset
    scale = 1.0 + rng.uniform(-amount, amount, size=len(PLANT_JITTER_FIELDS))
    return dataclasses.replace(
        preset, **{f: getattr(preset, f) * float(s) for f, s in zip(PLANT_JITTER_FIELDS, scale)}
    )


TRAIN_REWARD = RewardConfig(spacing_scale_m=2.0, w_accel=0.01, w_jerk=0.001, w_yaw_rate=0.01)
"""The training reward: the environment's, weighted towards the spacing error the metrics
measure (a steeper spacing term, lighter comfort terms). With the environment's default
weights the learner traded spacing accuracy for smoothness and ended worse than its base
on p95 platooning error."""


SCRATCH_REWARD = RewardConfig(spacing_scale_m=30.0, w_accel=0.005, w_jerk=0.0, w_yaw_rate=0.0)
"""The reward learning from scratch (no base): the spacing error, saturating only at 30 m,
and a light acceleration term. With ``TRAIN_REWARD``'s 2 m a follower that fell behind
sees no gradient back, and its comfort terms pay an exploring policy to creep (a slow car
turns and accelerates less); the light acceleration term damps the speed oscillation of
a spacing-only reward (p95 2.46 -> 1.89 m at PER 0)."""

TRAIN_SHAPING = Shaping(weight=1.0, gap_scale_m=1.0, path_scale_m=2.0, heading_scale_rad=0.5)
"""The terms training adds to the reward (``train.shaping``), with or without a base: from
scratch it is what made the followers keep the road; on the ``paper`` base the default
600k-step residual run went from p95 0.660 / 0.637 / 0.907 m to 0.122 / 0.174 / 0.438 m at
PER 0 / 0.3 / 0.6 (held-out seeds 0-4, seed 0 run, 0 collisions both)."""

RESIDUAL_ACTION_BOUNDS = ((0.0, -math.pi / 2), (5.0, math.pi / 2))
"""Residual actions: the sum may use the whole action range (DESIGN.md, Action)."""
ABSOLUTE_ACTION_BOUNDS = ((0.0, -0.3), (3.0, 0.3))
"""Absolute actions (``--base none``): what the normalized actions ±1 mean. A range
sized to the task (the leader drives 1-2 m/s; a path correction needs tenths of a
radian) makes the initial policy's exploration noise a speed and steering noise a
follower survives, instead of swerves of up to ±π/2."""


@dataclass(frozen=True)
class EnvSpec:
    """The fixed part of the training environments.

    Attributes:
        n_followers: agents per environment (parameter sharing: all run one policy).
        base_policy: policy spec the network corrects (residual actions): a classical
            preset or TOML, or a plug-in policy (``module:Name``, ``file.py:Name``; it
            brings its member config and rate, and trains on the per-convoy path);
            ``""``: none, the network's action is absolute.
        residual_scale: SI size of a full-scale residual ``[m/s, rad]``.
        member: the followers' member configuration (its layout is the policy's); None:
            the base policy's, or ``MemberConfig()`` without a base. A base runs with
            this member configuration.
        control_rate_hz: control and plant rate, Hz; None: the base policy's, else 20.
        action_low, action_high: absolute actions: SI values of the normalized actions -1
            and +1; residual actions: the SI bounds of the sum
            (``[speed_mps, heading_change_rad]``). None: ``RESIDUAL_ACTION_BOUNDS`` with
            a base, ``ABSOLUTE_ACTION_BOUNDS`` without.
        max_time_s: episode length cap, seconds (None: the scenario's duration).
        reward: the reward's weights (``openconvoy.envs.reward``); None: ``TRAIN_REWARD``
            with a base, ``SCRATCH_REWARD`` without.
        shaping: the training environments' terms on top of ``reward``
            (``train.shaping``: the last metre of the gap, the offset from the
            predecessor's trail); None: ``TRAIN_SHAPING``.
        reward_fn: a reward plug-in (``module:Name``, ``file.py:Name`` or an
            ``openconvoy.rewards`` entry point, ``?key=value`` arguments; ``core.plugins``):
            a class or factory whose object is called per follower per step as
            ``(reward, info, observation) -> float`` with the environment's reward (the
            weights of ``reward`` plus ``shaping``), the agent's info (``ConvoyEnv``'s
            ``INFO_KEYS``, SI units) and its observation; what it returns is the reward
            learned from. ``""``: none. It runs in Python: training takes the per-convoy
            path (docs/your-controller.md).
        obs_features: an observation-features plug-in (``module:Name``, ``file.py:Name``
            or an ``openconvoy.features`` entry point, ``?key=value`` arguments): an object
            called ``(observation) -> 1-D array`` whose numbers are appended to each
            observation the network sees; the trained policy records it and computes the
            same features wherever it runs (``LearnedMeta.obs_features``). ``""``: none.
        emergency_stop: the simulator's braking-aware emergency stop (a latched stop of a
            follower about to hit its predecessor) during training; None: on with a base,
            off without. Learning from scratch, a policy whose exploration trips the
            latched stop sits stopped for the rest of the episode whatever it does, and
            learns only to creep; without it, a collision ends the episode with its
            penalty, a signal it can learn from. Sim and deploy keep the stop on.
    """

    n_followers: Annotated[int, Range(1, 1000)] = 2
    base_policy: str = "paper"
    residual_scale: tuple[float, float] = (1.0, 0.1)
    member: MemberConfig | None = None
    control_rate_hz: Annotated[float, Range(0.0, 100.0, lo_open=True)] | None = None
    action_low: tuple[float, float] | None = None
    action_high: tuple[float, float] | None = None
    max_time_s: Annotated[float, Range(0.0, 7 * 86400.0, lo_open=True)] | None = None
    reward: RewardConfig | None = None
    shaping: Shaping | None = None
    emergency_stop: bool | None = None
    reward_fn: str = ""
    obs_features: str = ""
    plugin_base: str = dataclasses.field(init=False, default="", repr=False, compare=False)
    """The plug-in spec of a plug-in residual base (``module:Name?k=v``; "" for a
    classical base or none): ``base_policy`` resolved."""

    def __post_init__(self) -> None:
        if self.reward_fn:
            self.make_reward_fn()  # loads, takes its arguments, is callable: else one line
        if self.obs_features:
            self.make_features(MemberConfig().layout.size)  # loads: else one line
        bounds = RESIDUAL_ACTION_BOUNDS if self.base_policy else ABSOLUTE_ACTION_BOUNDS
        for name, default in zip(("action_low", "action_high"), bounds):
            if getattr(self, name) is None:
                object.__setattr__(self, name, default)
        if self.reward is None:
            object.__setattr__(self, "reward", TRAIN_REWARD if self.base_policy else SCRATCH_REWARD)
        if self.emergency_stop is None:
            object.__setattr__(self, "emergency_stop", bool(self.base_policy))
        if self.shaping is None:
            object.__setattr__(self, "shaping", TRAIN_SHAPING)
        for name in ("action_low", "action_high", "residual_scale"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        plugin = plugin_of(self.base_policy) if self.base_policy else None
        object.__setattr__(self, "plugin_base", "" if plugin is None else join_args(*plugin[:2]))
        base_member: MemberConfig | None = None
        base_rate = 20.0
        if plugin is not None:  # a plug-in base: its own member side and rate
            p = self.make_plugin_base()
            base_member, base_rate = p.member_config, p.control_rate_hz
            if base_member is not None and self.member not in (None, base_member):
                raise ConfigError(
                    f"base {self.base_policy} runs on its own member_config; leave member unset"
                )
        elif self.base_policy:
            base = classical_config(self.base_policy)
            base_member, base_rate = base.member, base.control_rate_hz
        if self.member is None:
            object.__setattr__(self, "member", base_member or MemberConfig())
        if self.control_rate_hz is None:
            object.__setattr__(self, "control_rate_hz", base_rate)
        if len(self.residual_scale) != 2 or min(self.residual_scale) < 0:
            raise ConfigError(
                f"residual_scale must be two non-negative numbers, got {self.residual_scale}"
            )
        if self.n_followers < 1:
            raise ConfigError(f"n_followers must be at least 1, got {self.n_followers}")
        low, high = self.bounds
        if len(low) != 2 or len(high) != 2:
            raise ConfigError("action_low and action_high are [speed_mps, heading_change_rad]")
        if not all(lo < hi for lo, hi in zip(low, high)):
            raise ConfigError(f"action_low {low} must lie below action_high {high}")
        if max(abs(low[1]), abs(high[1])) > math.pi / 2:
            raise ConfigError("the heading-change range must lie within ±π/2")
        if self.rate_hz <= 0:
            raise ConfigError(f"control_rate_hz must be positive, got {self.control_rate_hz}")

    @property
    def member_config(self) -> MemberConfig:
        """The resolved member configuration (never None after construction)."""
        assert self.member is not None
        return self.member

    @property
    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The resolved ``(action_low, action_high)``."""
        assert self.action_low is not None and self.action_high is not None
        return self.action_low, self.action_high

    @property
    def extra(self) -> Shaping:
        """The resolved ``shaping``."""
        assert self.shaping is not None
        return self.shaping

    @property
    def rate_hz(self) -> float:
        """The resolved control rate, Hz."""
        assert self.control_rate_hz is not None
        return self.control_rate_hz

    def make_reward_fn(self) -> Any:
        """A new instance of the reward plug-in (None without one)."""
        if not self.reward_fn:
            return None
        from openconvoy.core import plugins

        where = f"reward_fn {self.reward_fn}"
        obj, args = plugins.resolve(self.reward_fn, "reward", where)
        fn = plugins.construct(obj, args, where)
        plugins.check_methods(fn, {"__call__": 3}, where)
        return fn

    def make_features(self, size: int | None = None) -> tuple[Any, int]:
        """The observation-features plug-in and the count it appends ``(None, 0)`` without
        one), checked on an observation of ``size`` (default: this member's layout)."""
        if not self.obs_features:
            return None, 0
        from openconvoy.core import plugins

        n = self.member_config.layout.size if size is None else size
        return plugins.features(self.obs_features, n, f"obs_features {self.obs_features}")

    def make_plugin_base(self) -> Any:
        """A new instance of the plug-in residual base (``policies.plugin``)."""
        from openconvoy.policies.plugin import load_plugin_policy

        return load_plugin_policy(self.plugin_base)

    def base_config(self) -> ClassicalConfig | None:
        """The residual base as it runs here: the base policy with this member config and
        control rate (what the trained policy records), or None (no base, or a plug-in
        base: ``plugin_base``)."""
        if not self.base_policy or self.plugin_base:
            return None
        return dataclasses.replace(
            classical_config(self.base_policy),
            member=self.member_config,
            control_rate_hz=self.rate_hz,
        )


class RandomizedConvoyEnv(ParallelEnv):
    """``ConvoyEnv`` with a world redrawn at every ``reset`` and normalized actions.

    ``reset(seed=s)`` reseeds the draws (the same seed gives the same worlds and episodes
    for the same actions); ``reset()`` continues the sequence. ``world`` is the current
    episode's draw, ``env`` the ConvoyEnv running it.
    """

    metadata = {
        "name": "openconvoy_randomized_v0",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
    }

    def __init__(
        self, spec: EnvSpec, randomization: Randomization, render_mode: str | None = None
    ) -> None:
        self.spec_ = spec
        self.randomization = randomization
        self.render_mode = render_mode
        self.possible_agents = [f"follower_{i}" for i in range(1, spec.n_followers + 1)]
        self.agents: list[str] = []
        base = spec.base_config()
        self._bases: dict[str, Any] = (
            {a: ClassicalPolicy(base) for a in self.possible_agents} if base is not None else {}
        )
        if spec.plugin_base:  # a plug-in residual base, one object per follower
            self._bases = {a: spec.make_plugin_base() for a in self.possible_agents}
        self._obs: dict[str, np.ndarray] = {}
        self._reward_fn = spec.make_reward_fn()
        self._features, n_features = spec.make_features()
        size = spec.member_config.layout.size + n_features
        self._obs_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)
        self._act_space = gymnasium.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self._rng = np.random.default_rng()
        self.world: EpisodeWorld | None = None
        self.env: ConvoyEnv | None = None

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._act_space

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        s = self.spec_
        self.world = w = draw_world(self.randomization, s.n_followers, self._rng)
        self.env = ConvoyEnv(
            w.scenario,
            n_followers=None if w.vehicles is not None else s.n_followers,
            member_config=s.member_config,
            loss=w.loss,
            control_rate_hz=s.rate_hz,
            gps_noise_m=w.gps_noise_m,
            max_time_s=s.max_time_s,
            render_mode=self.render_mode,
            vehicle_presets=w.vehicles,
            reward_config=s.reward,
            emergency_stop=bool(s.emergency_stop),
        )
        obs, infos = self.env.reset(seed=int(self._rng.integers(2**31 - 1)), options=options)
        for b in self._bases.values():
            b.reset()
        self.agents = list(self.env.agents)
        self._obs = obs
        return self._extended(obs), infos

    def _extended(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """What the network sees: each observation with the features plug-in's numbers
        appended (``EnvSpec.obs_features``; the observation itself without one)."""
        fn = self._features
        if fn is None:
            return obs
        return {
            a: np.concatenate([o, np.asarray(fn(o), dtype=np.float32)]).astype(np.float32)
            for a, o in obs.items()
        }

    def step(self, actions: dict[str, np.ndarray]):
        if self.env is None:
            raise RuntimeError("step() before reset()")
        s = self.spec_
        si = {}
        for a, act in actions.items():
            base = self._bases[a].act(self._obs[a]) if self._bases else None
            si[a] = compose_action(act, *s.bounds, base, s.residual_scale)
        obs, rewards, term, trunc, infos = self.env.step(si)
        if s.extra.active:
            layout = s.member_config.layout
            for a in rewards:
                err = infos[a].get("platooning_error_m")
                e = np.nan if err is None else err
                rewards[a] += float(s.extra.bonus(layout, np.array(e), obs[a]))
        if self._reward_fn is not None:  # the researcher's reward (EnvSpec.reward_fn)
            fn = self._reward_fn
            rewards = {a: float(fn(r, infos[a], obs[a])) for a, r in rewards.items()}
        self._obs = obs
        self.agents = list(self.env.agents)
        return self._extended(obs), rewards, term, trunc, infos

    def render(self) -> np.ndarray | None:
        return None if self.env is None else self.env.render()

    def close(self) -> None:
        if self.env is not None:
            self.env.close()
