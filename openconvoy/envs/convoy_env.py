"""ConvoyEnv: the convoy as a PettingZoo ``ParallelEnv``; followers are the agents.

One tick (``dt = 1 / control_rate_hz``) is the vehicle's (DESIGN.md, One member, two
worlds): the simulation behind the API is a ``ConvoyWorld`` (``envs.world``: plant,
channel, members, sensors, faults) that drives each member through ``core.tick``. Each
follower's action ``[speed_mps, heading_change_rad]`` is checked, clipped to the action
space and supervised by its member's staleness ladder; the leader's setpoints come from
the scenario's driver; safety stops and faults are the world's (``safety_events``).

Termination: a collision (a follower closer to its predecessor than the sum of their half
lengths, centre to centre) ends the episode for everybody. Truncation: the scenario's
duration (or ``max_time_s``). Reward: ``openconvoy.envs.reward``. Infos, per agent per step:
``INFO_KEYS``. ``log_rows()`` gives the DESIGN.md log rows of the current tick.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from openconvoy.comms.loss import LossConfig, as_loss_config
from openconvoy.core import tick as member_tick
from openconvoy.core.config import Range, check_number
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_fault_times, check_faults, parse_fault
from openconvoy.core.member import ConvoyMember, MemberConfig, member_config_for
from openconvoy.core.policy import PolicyFailure
from openconvoy.core.state import VehicleState
from openconvoy.envs.channel import Channel
from openconvoy.envs.compiled import CompiledConvoy, backend_choice, python_only_reason
from openconvoy.envs.forgery import Authentication
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.render import draw_convoy
from openconvoy.envs.reward import RewardConfig, reward
from openconvoy.envs.scenarios import Scenario, is_traffic_scenario, make_scenario
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset
from openconvoy.envs.world import ConvoyWorld, TickRecord
from openconvoy.logs import snapshot_rows

if TYPE_CHECKING:
    from openconvoy.envs.vector.plant import VectorPlant

AGENT_PREFIX = "follower_"

INFO_KEYS: tuple[str, ...] = (
    "t_s",
    "gap_m",
    "desired_gap_m",
    "platooning_error_m",
    "spacing_error_m",
    "speed_mps",
    "accel_mps2",
    "leader_speed_mps",
    "cmd_speed_mps",
    "cmd_heading_change_rad",
    "mode",
    "collision",
    "msgs_sent",
    "msgs_received",
    "msgs_kept",
    "msgs_lost",
    "pred_msg_age_s",
    "policy_errors",
)
"""Per-agent info keys. ``gap_m``: ground-truth centre-to-centre distance to the immediate
predecessor; ``desired_gap_m``, ``spacing_error_m`` (path-based, from R^i) and
``pred_msg_age_s`` from the member; ``platooning_error_m`` = |gap - desired gap| (the
metric); ``msgs_received``/``msgs_lost``: messages the channel delivered to / dropped on
the way to this vehicle (cumulative); ``msgs_kept``: those its Rx gate kept; ``cmd_*``: the
action applied this tick (after the ladder). A value that does not exist yet (no message
heard, so no spacing error or message age; no command before the first step) is ``None``,
never NaN, so infos compare equal between identical runs."""


def _opt(v: float) -> float | None:
    return None if v != v else v  # NaN -> None


def check_rate_and_noise(control_rate_hz: float, gps_noise_m: float) -> None:
    """``ConfigError`` naming the argument unless the control rate (Hz) is positive and
    finite and the GPS noise (m, one sigma) finite and >= 0."""
    for name, value, allowed in (
        ("control_rate_hz", control_rate_hz, Range(lo=0.0, lo_open=True)),
        ("gps_noise_m", gps_noise_m, Range(lo=0.0)),
    ):
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: expected a number, got {value!r}") from None
        check_number(number, name, allowed)


MAX_FOLLOWERS = 1000
"""Most followers a convoy env takes (``RunConfig``'s ``[convoy] n_followers`` bound)."""
MAX_TIME_S = 604800.0
"""Longest episode an env takes (s): a week, ``RunConfig``'s ``duration_s`` bound."""


def check_episode_args(n_followers: object, max_time_s: object) -> None:
    """``ConfigError`` naming the argument unless ``n_followers`` is None or an integer in
    1..``MAX_FOLLOWERS`` and ``max_time_s`` None or a number in (0, ``MAX_TIME_S``] s
    (issue 22, D68/D69)."""
    if n_followers is not None:
        if isinstance(n_followers, bool) or not isinstance(n_followers, (int, np.integer)):
            raise ConfigError(f"n_followers: expected an integer, got {n_followers!r}")
        if not 1 <= int(n_followers) <= MAX_FOLLOWERS:
            raise ConfigError(f"n_followers must be in 1..{MAX_FOLLOWERS}, got {n_followers}")
    if max_time_s is not None:
        try:
            value = float(max_time_s)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ConfigError(f"max_time_s: expected a number, got {max_time_s!r}") from None
        check_number(value, "max_time_s", Range(lo=0.0, hi=MAX_TIME_S, lo_open=True))


def check_action(agent: str, action: object) -> None:
    """``ValueError`` naming ``agent`` unless ``action`` is ``[speed, heading change]``: two
    real numbers (shape (2,); NaN or inf pass: they are the policy's error, a stop), or a
    ``PolicyFailure`` (a guarded policy that raised or overran: a stop too)."""
    if type(action) is np.ndarray and action.shape == (2,) and action.dtype.kind in "fiu":
        return  # the common case, without a conversion
    if isinstance(action, PolicyFailure):
        return
    try:
        arr = np.asarray(action)
    except Exception:  # noqa: BLE001 - anything not an array is the message's case
        arr = None
    if arr is None or arr.shape != (2,) or arr.dtype.kind not in "fiu":
        what = (
            "None"
            if action is None
            else " ".join(f"{type(action).__name__} {action!r}".split())[:80]
        )
        shape = "" if arr is None else f" shape {arr.shape} dtype {arr.dtype}"
        raise ValueError(
            f"action of {agent}: expected shape (2,) numbers [speed, heading change], "
            f"got {what}{shape}"
        )


def agent_name(vehicle_id: int) -> str:
    """The agent name of follower ``vehicle_id`` (1 = first follower)."""
    return f"{AGENT_PREFIX}{vehicle_id}"


class ConvoyEnv(ParallelEnv):
    """A convoy of a scenario-driven leader and ``n`` learning (or scripted) followers.

    Args:
        scenario: a spec (``paper``, ``track``, ``emergency-braking``,
            ``track-file:PATH``, or a ``highway-*`` spec, which makes a
            ``TrafficConvoyEnv``) or a ``Scenario`` object.
        n_followers: convoy size for spec scenarios (default: the scenario's, 2).
        member_config: the member side of the followers' implementation (topology,
            trigger, spacing, ladder, layout M and k); default: ``MemberConfig`` with the
            scenario's spacing. Pass a classical policy's ``member_config`` to run it.
        loss: packet loss and latency of every link: a ``LossConfig``, or a packet error
            rate for Bernoulli loss (default: perfect links).
        per: the packet error rate of every link, in [0, 1] (``ConvoyEnv(per=0.2)``;
            replaces ``loss``'s).
        control_rate_hz: control and plant rate; ``dt = 1 / control_rate_hz`` seconds.
        gps_noise_m: standard deviation of white Gaussian noise on the positions members
            observe and broadcast (metres, per axis); 0 = exact.
        max_time_s: episode length (default: the scenario's duration).
        render_mode: None or ``"rgb_array"``.
        plant_presets: the vehicles as they drive, when they differ from the presets
            the members and the scenario know (``fit-plant --convoy``'s fitted plants;
            docs/calibration.md); default: the same.
        vehicle_presets: replace the scenario's vehicles (names, TOML paths or presets,
            leader first); sets the convoy size.
        reward_config: weights of the reward (``openconvoy.envs.reward``).
        faults: ``core.faults.Fault`` objects or ``KIND:VEHICLE@T_S`` specs, injected
            at their times (ConfigError naming a bad one).
        gap_margin_m: margin (m, between bumpers) of the braking-aware emergency stop;
            None = each follower's preset default (``core.safety.for_vehicle``).
        emergency_stop: apply that rule (default True).
        auth: members authenticate what they receive (modelled: ``envs.forgery``), so the
            messages of a ``forge`` fault are rejected and counted (``forged_rejected``);
            False: they are believed (default True, as on vehicles with keys).
        backend: ``compiled`` steps through the batched kernels (``envs.compiled``,
            numba), ``python`` through ``envs.world`` (the reference, what vehicles
            run), ``auto`` the compiled tick where it can run this convoy; default: the
            ``OPENCONVOY_ENV_BACKEND`` environment variable, else ``auto``. ``sim``,
            ``members``, ``channel``, ``auth`` and the log rows are the Python path's.
    """

    metadata = {
        "name": "openconvoy_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 20,
        "is_parallelizable": True,
    }
    LOG_EXTRA_COLUMNS: tuple[str, ...] = ()
    """Columns this env's log rows carry beyond DESIGN.md's (a run writes them)."""
    WORLD: type[ConvoyWorld] = ConvoyWorld
    """The simulation behind the API (a world with more in it subclasses it)."""

    def __new__(cls, scenario: str | Scenario = "paper", *args: Any, **kwargs: Any) -> ConvoyEnv:
        # Highway scenarios bring traffic: ``ConvoyEnv("highway-cut-in")`` is a
        # TrafficConvoyEnv (needs the ``traffic`` extra).
        if cls is ConvoyEnv and is_traffic_scenario(scenario):
            from openconvoy.envs.traffic.env import TrafficConvoyEnv

            cls = TrafficConvoyEnv
        return super().__new__(cls)

    def __init__(
        self,
        scenario: str | Scenario = "paper",
        n_followers: int | None = None,
        member_config: MemberConfig | None = None,
        loss: LossConfig | float | None = None,
        control_rate_hz: float = 20.0,
        gps_noise_m: float = 0.0,
        max_time_s: float | None = None,
        render_mode: str | None = None,
        vehicle_presets: Sequence[VehiclePreset | str] | None = None,
        reward_config: RewardConfig | None = None,
        faults: Sequence[Fault | str] = (),
        gap_margin_m: float | None = None,
        emergency_stop: bool = True,
        auth: bool = True,
        per: float | None = None,
        plant_presets: Sequence[VehiclePreset | str] | None = None,
        backend: str | None = None,
    ) -> None:
        check_rate_and_noise(control_rate_hz, gps_noise_m)
        check_episode_args(n_followers, max_time_s)
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        scenario = _resolve_scenario(scenario, n_followers, vehicle_presets)
        self.scenario = scenario
        self.presets = tuple(scenario.presets)
        self.n_vehicles = n = scenario.n_vehicles
        self.control_rate_hz = float(control_rate_hz)
        self.dt = 1.0 / self.control_rate_hz
        self.max_time_s = float(scenario.duration_s if max_time_s is None else max_time_s)
        self.max_steps = max(1, int(round(self.max_time_s / self.dt)))
        self.gps_noise_m = float(gps_noise_m)
        self.render_mode = render_mode
        self.reward_config = reward_config or RewardConfig()
        self.loss = as_loss_config(loss, per)
        self.member_config = member_config_for(member_config, scenario.spacing)

        parsed = tuple(f if isinstance(f, Fault) else parse_fault(f) for f in faults)
        check_faults(parsed, n)  # the vehicle first, then the time: the more telling line
        check_fault_times(parsed, self.max_time_s)
        self._faults = parsed
        self._compiled = self._compile(backend, plant_presets, gap_margin_m, emergency_stop, auth)
        self.backend = "python" if self._compiled is None else "compiled"
        """The path this env steps through: ``compiled`` or ``python`` (``envs.compiled``)."""
        self.possible_agents = [agent_name(i) for i in range(1, n)]
        self.agents: list[str] = []
        self._was_reset = False
        self._agent_index = {a: i for i, a in enumerate(self.possible_agents, start=1)}
        self._observation_spaces, self._action_spaces = self._spaces()
        self._road: np.ndarray | None = None
        self._seed_seq: np.random.SeedSequence | None = None
        if self._compiled is not None:
            return
        self._sim = self.WORLD(
            scenario,
            self.member_config,
            self.loss,
            self.dt,
            self.gps_noise_m,
            parsed,
            gap_margin_m,
            bool(emergency_stop),
            bool(auth),
            plant_presets=None
            if plant_presets is None
            else [p if isinstance(p, VehiclePreset) else vehicle_preset(p) for p in plant_presets],
        )

    def _compile(
        self,
        backend: str | None,
        plant_presets: object,
        gap_margin_m: float | None,
        emergency_stop: bool,
        auth: bool,
    ) -> CompiledConvoy | None:
        """The compiled tick of this convoy (``envs.compiled``), or None for the Python
        path: asked for, or ``auto`` where the kernels cannot run it (numba missing, a
        traffic world, a plug-in σ or τ...); ``ConfigError`` when ``compiled`` cannot."""
        choice = backend_choice(backend)
        if choice == "python":
            return None
        why = python_only_reason(
            self.scenario, type(self).WORLD is ConvoyWorld, plant_presets, self.render_mode
        )
        if why is None:
            try:
                return CompiledConvoy(
                    self.scenario,  # type: ignore[arg-type]  # a PathScenario (checked)
                    self.member_config,
                    self.loss,
                    self.control_rate_hz,
                    self.gps_noise_m,
                    self.max_time_s,
                    self.reward_config,
                    self._faults,
                    gap_margin_m,
                    bool(emergency_stop),
                    bool(auth),
                )
            except ImportError:
                why = "numba (the batched extra) is not installed"
            except ConfigError as exc:
                why = str(exc)
        if choice == "compiled":
            raise ConfigError(f"backend='compiled': {why}")
        return None

    @property
    def sim(self) -> ConvoyWorld:
        """The simulated convoy (``envs.world.ConvoyWorld``): the Python path's only."""
        sim = self.__dict__.get("_sim")
        if sim is None:
            raise AttributeError(
                "sim: this env steps through the compiled tick, which has no ConvoyWorld; "
                "ConvoyEnv(..., backend='python') (or OPENCONVOY_ENV_BACKEND=python) has one"
            )
        return sim

    def _spaces(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """Observation and action spaces per agent; the action space is the clip every
        world applies (``core.tick.ActionBounds``), bit for bit."""
        low, high = self.member_config.layout.bounds()
        obs = {a: gymnasium.spaces.Box(low, high, dtype=np.float32) for a in self.possible_agents}
        act = {}
        for a, i in self._agent_index.items():
            b = member_tick.ActionBounds.float32(self.presets[i].max_speed_mps)
            act[a] = gymnasium.spaces.Box(
                low=np.array([0.0, -b.max_heading_change_rad], dtype=np.float32),
                high=np.array([b.max_speed_mps, b.max_heading_change_rad], dtype=np.float32),
                dtype=np.float32,
            )
        return obs, act

    # --- PettingZoo API ------------------------------------------------------------------

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self._action_spaces[agent]

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """Start an episode. The same ``seed`` gives the same episode for the same actions;
        ``seed=None`` continues the previous seed's sequence (fresh entropy the first time)."""
        self._was_reset = True
        self.agents = self.possible_agents[:]
        fast = self._compiled
        if fast is not None:
            return fast.reset(seed, self.agents)
        if seed is not None:
            self._seed_seq = np.random.SeedSequence(seed)
        elif self._seed_seq is None:
            self._seed_seq = np.random.SeedSequence()
        self.sim.reset(self._seed_seq)
        return self._observations(), self._infos()

    def step(
        self, actions: dict[str, np.ndarray]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Advance one tick with every live agent's action (SI units, clipped to the space).
        ``ValueError`` naming the agent for an action that is not two numbers, or a key
        that is no agent; NaN or inf is the policy's error (that follower stops)."""
        if not self.agents:
            if not self._was_reset:
                raise RuntimeError("step() called before reset(); call reset() first")
            raise RuntimeError("step() called on a finished episode; call reset()")
        names = self.possible_agents
        try:
            ordered = [actions[a] for a in names]
        except KeyError as exc:
            raise KeyError(f"no action for {exc.args[0]}") from None
        # Every agent has an action, so an extra key makes the dict longer.
        unknown = set(actions) - set(names) if len(actions) > len(names) else ()
        if unknown:
            raise ValueError(
                f"actions for unknown agents {sorted(map(str, unknown))}; agents: {', '.join(names)}"
            )
        for a, action in zip(names, ordered):
            check_action(a, action)
        fast = self._compiled
        if fast is not None:  # the compiled tick (envs.compiled)
            obs, rewards, terminations, truncations, infos, ended = fast.step(ordered, self.agents)
            if ended:
                self.agents = []
            return obs, rewards, terminations, truncations, infos
        sim = self.sim
        accel_before = sim.truth.accel
        sim.decide(ordered)
        sim.advance()
        inv_dt = 1.0 / self.dt
        tr = sim.truth
        jerk = [(a1 - a0) * inv_dt for a0, a1 in zip(accel_before[1:], tr.accel[1:])]
        rewards_list = reward(
            self.reward_config,
            [g - d for g, d in zip(sim.gaps, sim.desired)],
            tr.accel[1:],
            jerk,
            tr.yaw_rate[1:],
            sim.collided,
        )
        done = sim.terminated()
        trunc = sim.step_count >= self.max_steps and not done
        agents = self.agents
        rewards = dict(zip(agents, rewards_list))
        terminations = dict.fromkeys(agents, done)
        truncations = dict.fromkeys(agents, trunc)
        obs, infos = self._observations(), self._infos()
        if done or trunc:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """``rgb_array``: an H x W x 3 uint8 picture of the convoy (None without a mode)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without render_mode; nothing drawn")
            return None
        if self._road is None and self.scenario.path is not None:
            path = self.scenario.path
            self._road = (
                path.points if len(path.points) == 2 and not path.closed else path.sample(0.5)
            )
        modes = ["leader", *self.sim.modes[1:]]
        return draw_convoy(
            self.plant.x,
            self.plant.y,
            self.plant.heading,
            np.array(self.sim.lengths),
            np.array(self.sim.widths),
            modes,
            self._road,
        )

    def close(self) -> None:
        pass

    @classmethod
    def aec(cls, **kwargs: Any):
        """The AEC version (PettingZoo's ``parallel_to_aec``) of ``ConvoyEnv(**kwargs)``."""
        return parallel_to_aec(cls(**kwargs))

    # --- sim runner helpers ---------------------------------------------------------------

    @property
    def vehicle_lengths(self) -> dict[int, float]:
        """Vehicle id -> length (m): the collision thresholds ``core.metrics`` wants."""
        return {i: p.length_m for i, p in enumerate(self.presets)}

    @property
    def delivery_ratio(self) -> float:
        """Messages delivered / (delivered + lost) over all links so far (NaN before any)."""
        if self._compiled is not None:
            return self._compiled.delivery_ratio()
        return self.sim.channel.delivery_ratio()

    def log_rows(self) -> list[dict[str, Any]]:
        """DESIGN.md log rows for every vehicle (leader first) of the tick ``step()`` just
        completed: the state at that tick's ``t_s`` and the setpoints computed from it, as a
        vehicle logs them (empty right after ``reset``).

        The state is the plant's (ground truth); lat/lon come from the scenario's origin.
        ``msgs_received``/``msgs_lost`` count what the channel delivered to / dropped for
        the vehicle (the member's Rx gate may discard some of the received ones; infos
        carry ``msgs_kept``).
        """
        record = self.sim.record
        return [] if record is None else self._rows(record)

    def final_log_rows(self) -> list[dict[str, Any]]:
        """Rows of the state the episode ended in (a collision shows here), with empty
        commands: a run logs them once after its last ``step``."""
        return self._rows(self.sim.final_record())

    def _rows(self, record: TickRecord) -> list[dict[str, Any]]:
        return snapshot_rows(self.sim.snapshot(record))

    # --- the world's parts, for callers and tests ----------------------------------------

    @property
    def t(self) -> float:
        """Simulated time (s)."""
        if self._compiled is not None:
            return float(self._compiled.vec.t[0])
        return self.sim.t

    @property
    def step_count(self) -> int:
        """Steps since reset."""
        if self._compiled is not None:
            return int(self._compiled.vec.step_count[0])
        return self.sim.step_count

    @property
    def plant(self) -> BicyclePlant | VectorPlant:
        """The vehicles' plant (the compiled tick's: ``x``, ``y``, ``speed``,
        ``heading``, ``accel``, ``yaw_rate`` arrays alike, one entry per vehicle)."""
        if self._compiled is not None:
            return self._compiled.vec.plant
        return self.sim.plant

    @property
    def channel(self) -> Channel[VehicleState]:
        """The V2V channel."""
        return self.sim.channel

    @property
    def members(self) -> list[ConvoyMember]:
        """The ``ConvoyMember`` of each vehicle (the leader first)."""
        return self.sim.members

    @property
    def faults(self) -> tuple[Fault, ...]:
        """The injected faults."""
        return self._faults

    @property
    def auth(self) -> Authentication:
        """Receivers' verification (``forge`` faults, ``security.auth``)."""
        return self.sim.auth

    @property
    def safety_events(self) -> list[tuple[float, int, str]]:
        """(t s, vehicle, reason): faults injected, refused actions and emergency stops."""
        if self._compiled is not None:
            return self._compiled.safety_events()
        return self.sim.safety_events

    @property
    def forged_rejected(self) -> list[int]:
        """Forged messages each member rejected so far (``forge`` faults, ``security.auth`` on)."""
        if self._compiled is not None:
            return [int(v) for v in self._compiled.vec.forged_rejected[0].tolist()]
        return list(self.sim.auth.rejected)

    # --- internals ---------------------------------------------------------------------

    def _observations(self) -> dict[str, np.ndarray]:
        frames = self.sim.frames
        return {a: frames[i].observation for i, a in enumerate(self.agents, start=1)}

    def _infos(self) -> dict[str, dict[str, Any]]:
        return agent_infos(self.sim, self.agents, self.n_vehicles)


def agent_infos(
    sim: ConvoyWorld, agents: Sequence[str], n_vehicles: int
) -> dict[str, dict[str, Any]]:
    """The ``INFO_KEYS`` of every live agent (follower ``i`` is ``agents[i - 1]``) at the
    world's present tick."""
    speed, accel = sim.truth.speed, sim.truth.accel
    gap, desired = sim.gaps, sim.desired
    record = sim.record
    if record is None:  # right after reset: nothing applied yet
        cmd_v = cmd_dh = [math.nan] * n_vehicles
    else:
        cmd_v, cmd_dh = record.cmd_speed, record.cmd_heading_change
    errors = sim.policy_errors
    out = {}
    for i, a in enumerate(agents, start=1):
        m, f = sim.members[i], sim.frames[i]
        out[a] = {
            "t_s": sim.t,
            "gap_m": gap[i - 1],
            "desired_gap_m": _opt(desired[i - 1]),
            "platooning_error_m": _opt(abs(gap[i - 1] - desired[i - 1])),
            "spacing_error_m": _opt(f.spacing_error_m),
            "speed_mps": speed[i],
            "accel_mps2": accel[i],
            "leader_speed_mps": speed[0],
            "cmd_speed_mps": _opt(cmd_v[i]),
            "cmd_heading_change_rad": _opt(cmd_dh[i]),
            "mode": sim.modes[i],
            "collision": sim.collided[i - 1],
            "msgs_sent": m.msgs_sent,
            "msgs_received": sim.rx[i],
            "msgs_kept": m.msgs_received,
            "msgs_lost": sim.lost[i],
            "pred_msg_age_s": _opt(f.pred_msg_age_s),
            "policy_errors": errors[i],
        }
    return out


def _resolve_scenario(
    scenario: str | Scenario,
    n_followers: int | None,
    vehicle_presets: Sequence[VehiclePreset | str] | None,
) -> Scenario:
    """The scenario object of a spec (with its convoy size and vehicles) or as given."""
    presets = None
    if vehicle_presets is not None:
        presets = [
            p if isinstance(p, VehiclePreset) else vehicle_preset(p) for p in vehicle_presets
        ]
    if isinstance(scenario, str):
        scenario = make_scenario(scenario, n_followers, presets)
    elif presets is not None or n_followers is not None:
        raise ConfigError(
            "n_followers and vehicle_presets apply to scenario specs, not Scenario objects"
        )
    if scenario.n_vehicles < 2:
        raise ConfigError("a convoy needs a leader and at least one follower")
    return scenario


def convoy_aec_env(**kwargs: Any):
    """The AEC version of ``ConvoyEnv(**kwargs)`` via PettingZoo's ``parallel_to_aec``."""
    return parallel_to_aec(ConvoyEnv(**kwargs))
