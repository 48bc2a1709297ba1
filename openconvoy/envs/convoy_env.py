"""ConvoyEnv: the convoy as a PettingZoo ``ParallelEnv``; followers are the agents.

One tick (``dt = 1 / control_rate_hz``), the same sequence a vehicle runs (DESIGN.md, One
member, two worlds):

1. each follower's action ``[speed_mps, heading_change_rad]`` goes through its member's
   staleness ladder (``supervise``, with the ranging sensor's reading when the vehicle has
   one); the leader's setpoints come from the scenario's driver;
2. the plant steps with speed and absolute heading setpoints (current heading + change);
3. every member takes its own state (with optional GPS noise on the position), its Tx gate
   decides whether to broadcast (the gate keeps its own check period), the channel applies
   loss and latency per link and delivers what is due, members keep what their Rx gate
   wants, and followers build their observations.

Safety, as on vehicles: a follower whose braking-aware gap rule fires (``core.safety``:
the gap between bumpers, less what braking at its limit from the closing speed takes, is
below the margin; the gap from its ranging sensor, else from its member's estimate of
the predecessor) stops for the rest of the episode, mode ``failsafe``; ``safety_events``
says when and why. Faults (``core.faults``: ``halt``, ``silent``, ``dead``) override a
vehicle's setpoints with a stop at its braking limit and/or mute its broadcasts from
their time on.

Termination: a collision (a follower closer to its predecessor than the sum of their half
lengths, centre to centre) ends the episode for everybody. Truncation: the scenario's
duration (or ``max_time_s``). Reward: ``openconvoy.envs.reward``. Infos, per agent per step:
``INFO_KEYS``. ``log_rows()`` gives the DESIGN.md log rows of the current tick.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv
from pettingzoo.utils.conversions import parallel_to_aec

from openconvoy.comms.geodesy import enu_to_geodetic
from openconvoy.comms.loss import LossConfig
from openconvoy.core import tick as member_tick
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_faults, parse_fault
from openconvoy.core.member import ConvoyMember, Frame, MemberConfig, member_config_for
from openconvoy.core.safety import BrakingGap, bumper_gap, for_vehicle
from openconvoy.core.state import VehicleState
from openconvoy.envs.channel import Channel
from openconvoy.envs.forgery import Authentication
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.render import draw_convoy
from openconvoy.envs.reward import RewardConfig, reward
from openconvoy.envs.scenarios import Scenario, is_traffic_scenario, make_scenario
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset

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
        loss: packet loss and latency of every link (default: perfect links).
        control_rate_hz: control and plant rate; ``dt = 1 / control_rate_hz`` seconds.
        gps_noise_m: standard deviation of white Gaussian noise on the positions members
            observe and broadcast (metres, per axis); 0 = exact.
        max_time_s: episode length (default: the scenario's duration).
        render_mode: None or ``"rgb_array"``.
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
    """

    metadata = {
        "name": "openconvoy_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 20,
        "is_parallelizable": True,
    }
    LOG_EXTRA_COLUMNS: tuple[str, ...] = ()
    """Columns this env's log rows carry beyond DESIGN.md's (a run writes them)."""

    def __new__(cls, scenario: str | Scenario = "paper", *args: Any, **kwargs: Any) -> ConvoyEnv:
        # Highway scenarios bring traffic: ``ConvoyEnv("highway-cut-in")`` is a
        # TrafficConvoyEnv (needs the ``traffic`` extra).
        if cls is ConvoyEnv and is_traffic_scenario(scenario):
            from openconvoy.envs.traffic_env import TrafficConvoyEnv

            cls = TrafficConvoyEnv
        return super().__new__(cls)

    def __init__(
        self,
        scenario: str | Scenario = "paper",
        n_followers: int | None = None,
        member_config: MemberConfig | None = None,
        loss: LossConfig | None = None,
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
    ) -> None:
        if control_rate_hz <= 0:
            raise ConfigError(f"control_rate_hz must be positive, got {control_rate_hz}")
        if gps_noise_m < 0:
            raise ConfigError(f"gps_noise_m must be >= 0, got {gps_noise_m}")
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        presets = None
        if vehicle_presets is not None:
            presets = [p if isinstance(p, VehiclePreset) else vehicle_preset(p) for p in vehicle_presets]
        if isinstance(scenario, str):
            scenario = make_scenario(scenario, n_followers, presets)
        elif presets is not None or n_followers is not None:
            raise ConfigError("n_followers and vehicle_presets apply to scenario specs, not Scenario objects")
        if scenario.n_vehicles < 2:
            raise ConfigError("a convoy needs a leader and at least one follower")
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
        self.loss = loss or LossConfig()
        self.member_config = member_config_for(member_config, scenario.spacing)

        self._lengths = [p.length_m for p in self.presets]
        self._widths = [p.width_m for p in self.presets]
        self._half_sum = [0.5 * (a + b) for a, b in zip(self._lengths[1:], self._lengths[:-1])]
        decels = [p.decel_max_mps2 for p in self.presets]
        self.members = [ConvoyMember(i, n, self.member_config, self._lengths, decels) for i in range(n)]
        self.faults = tuple(f if isinstance(f, Fault) else parse_fault(f) for f in faults)
        check_faults(self.faults, n)
        self.emergency_stop = bool(emergency_stop)
        self.auth = Authentication(n, required=bool(auth))
        self._forged = tuple(f for f in self.faults if f.forges)
        self._braking: list[BrakingGap | None] = [None] + [
            for_vehicle(p.decel_max_mps2, p.actuation_delay_s, p.speed_lag_s, p.length_m, gap_margin_m)
            for p in self.presets[1:]
        ]
        self.plant = BicyclePlant(self.presets, self.dt)
        self.channel: Channel[VehicleState] = Channel(n, self.loss)
        self._ranging = [(i, p.ranging) for i, p in enumerate(self.presets) if i > 0 and p.ranging]

        self.possible_agents = [agent_name(i) for i in range(1, n)]
        self.agents: list[str] = []
        self._agent_index = {a: i for i, a in enumerate(self.possible_agents, start=1)}
        size = self.member_config.layout.size
        self._observation_spaces = {
            a: gymnasium.spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)
            for a in self.possible_agents
        }
        # The action space and the clip every world applies (core.tick), bit for bit.
        self._bounds = [member_tick.ActionBounds.float32(p.max_speed_mps) for p in self.presets]
        self._action_spaces = {
            a: gymnasium.spaces.Box(
                low=np.array([0.0, -self._bounds[i].max_heading_change_rad], dtype=np.float32),
                high=np.array([self._bounds[i].max_speed_mps, self._bounds[i].max_heading_change_rad],
                              dtype=np.float32),
                dtype=np.float32,
            )
            for a, i in self._agent_index.items()
        }
        self._road: np.ndarray | None = None
        self._seed_seq: np.random.SeedSequence | None = None
        self.t = 0.0
        self.step_count = 0
        self._reset_arrays()

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
        if seed is not None:
            self._seed_seq = np.random.SeedSequence(seed)
        elif self._seed_seq is None:
            self._seed_seq = np.random.SeedSequence()
        ss_channel, ss_gps, ss_ranging, ss_scenario = self._seed_seq.spawn(4)
        self._gps_rng = np.random.default_rng(ss_gps)
        self._ranging_rng = np.random.default_rng(ss_ranging)
        self.scenario.reset(np.random.default_rng(ss_scenario))
        self.channel.reset(np.random.default_rng(ss_channel))
        self.auth.reset()
        init = self.scenario.initial_state()
        self.plant.reset(init.x, init.y, init.heading, init.speed)
        for m in self.members:
            m.reset()
        self.t = 0.0
        self.step_count = 0
        self._reset_arrays()
        self.agents = self.possible_agents[:]
        obs = self._tick()
        self._measure()
        return obs, self._infos()

    def step(
        self, actions: dict[str, np.ndarray]
    ) -> tuple[
        dict[str, np.ndarray],
        dict[str, float],
        dict[str, bool],
        dict[str, bool],
        dict[str, dict[str, Any]],
    ]:
        """Advance one tick with every live agent's action (SI units, clipped to the space)."""
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset()")
        plant = self.plant
        t = self.t
        cmd_v, cmd_dh = self._cmd_speed, self._cmd_dh
        ranging = self._ranging_readings()
        modes = self._modes
        names = self.possible_agents
        for i in range(1, self.n_vehicles):
            try:
                a = actions[names[i - 1]]
            except KeyError:
                raise KeyError(f"no action for {names[i - 1]}") from None
            reading = ranging.get(i) if ranging else None
            d = member_tick.decide(self.members[i], self._frames[i], a, self._bounds[i], reading)
            cmd_v[i], cmd_dh[i], modes[i] = d.speed_mps, d.heading_change_rad, d.mode
            if d.policy_error:
                self._policy_error(i, t, d.policy_error)
            if self._failed[i] or (self.emergency_stop and self._emergency(i, t, reading)):
                cmd_v[i] = cmd_dh[i] = 0.0
                modes[i] = "failsafe"
        X, Y, V, H, A, _ = self._truth
        v0, h0 = self.scenario.leader_command(t, X[0], Y[0], H[0], V[0])
        cmd_v[0] = v0
        cmd_dh[0] = (h0 - H[0] + math.pi) % (2 * math.pi) - math.pi
        if self.faults:
            self._apply_faults(t)
        self._keep_row_inputs()
        plant.step(cmd_v, [h + d for h, d in zip(H, cmd_dh)])
        self.step_count += 1
        self.t = self.step_count * self.dt
        obs = self._tick()
        self._measure()
        inv_dt = 1.0 / self.dt
        A_new, YR_new = self._truth[4], self._truth[5]
        jerk = [(a1 - a0) * inv_dt for a0, a1 in zip(A[1:], A_new[1:])]
        self._jerk = jerk

        rewards_list = reward(
            self.reward_config,
            [g - d for g, d in zip(self._gap, self._desired)],
            A_new[1:], jerk, YR_new[1:], self._collided,
        )
        done = self._terminated()
        trunc = self.step_count >= self.max_steps and not done
        agents = self.agents
        rewards = dict(zip(agents, rewards_list))
        terminations = dict.fromkeys(agents, done)
        truncations = dict.fromkeys(agents, trunc)
        infos = self._infos()
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
            self._road = path.points if len(path.points) == 2 and not path.closed else path.sample(0.5)
        modes = ["leader", *self._modes[1:]]
        return draw_convoy(
            self.plant.x, self.plant.y, self.plant.heading, np.array(self._lengths),
            np.array(self._widths), modes, self._road,
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
        return dict(enumerate(self._lengths))

    @property
    def delivery_ratio(self) -> float:
        """Messages delivered / (delivered + lost) over all links so far (NaN before any)."""
        return self.channel.delivery_ratio()

    def log_rows(self) -> list[dict[str, Any]]:
        """DESIGN.md log rows for every vehicle (leader first) of the tick ``step()`` just
        completed: the state at that tick's ``t_s`` and the setpoints computed from it, as a
        vehicle logs them (empty right after ``reset``).

        The state is the plant's (ground truth); lat/lon come from the scenario's origin.
        ``msgs_received``/``msgs_lost`` count what the channel delivered to / dropped for
        the vehicle (the member's Rx gate may discard some of the received ones; infos
        carry ``msgs_kept``).
        """
        return [] if self._row_inputs is None else self._rows(self._row_inputs)

    def final_log_rows(self) -> list[dict[str, Any]]:
        """Rows of the state the episode ended in (a collision shows here), with empty
        commands: a run logs them once after its last ``step``."""
        nan = [math.nan] * self.n_vehicles
        return self._rows(self._row_inputs_now(nan, nan))

    def _rows(self, inputs: tuple[Any, ...]) -> list[dict[str, Any]]:
        t, truth, cmd_v, cmd_dh, modes, gaps, member_values, rx, lost = inputs
        xs, ys, vs, hs, acs = truth[:5]
        lat, lon, _ = enu_to_geodetic(self.scenario.origin, np.array(xs), np.array(ys))
        rows = []
        # Keys in openconvoy.logs.COLUMNS order (the tests hold them to it).
        for i, (desired, spacing_error, age, sent) in enumerate(member_values):
            rows.append({
                "t_s": t,
                "vehicle_id": i,
                "x_m": xs[i],
                "y_m": ys[i],
                "lat_deg": float(lat[i]),
                "lon_deg": float(lon[i]),
                "speed_mps": vs[i],
                "heading_rad": hs[i],
                "accel_mps2": acs[i],
                "cmd_speed_mps": cmd_v[i],
                "cmd_heading_change_rad": cmd_dh[i],
                "mode": modes[i],
                "gap_m": gaps[i],
                "desired_gap_m": desired if i else math.nan,
                "spacing_error_m": spacing_error if i else math.nan,
                "msgs_sent": sent,
                "msgs_received": rx[i],
                "msgs_lost": lost[i],
                "pred_msg_age_s": age if i else math.nan,
            })
        return rows

    def _keep_row_inputs(self) -> None:
        """Snapshot what ``log_rows`` reports for this tick, before the plant moves on."""
        self._row_inputs = self._row_inputs_now(list(self._cmd_speed), list(self._cmd_dh))

    def _row_inputs_now(self, cmd_v: list[float], cmd_dh: list[float]) -> tuple[Any, ...]:
        return (
            round(self.t, 9),
            self._truth,
            cmd_v,
            cmd_dh,
            list(self._modes),
            [math.nan, *self._gap],
            [(f.desired_gap_m, f.spacing_error_m, f.pred_msg_age_s, m.msgs_sent)
             for f, m in zip(self._frames, self.members)],
            [int(v) for v in self._rx],
            [int(v) for v in self._lost],
        )

    # --- internals ---------------------------------------------------------------------

    def _terminated(self) -> bool:
        """Does the episode end at this tick? (A world with more in it, such as traffic,
        adds its own collisions.)"""
        return any(self._collided)

    def _reset_arrays(self) -> None:
        n = self.n_vehicles
        self._cmd_speed = [0.0] * n
        self._cmd_dh = [0.0] * n
        self._row_inputs: tuple[Any, ...] | None = None
        self._modes = ["coop"] * n
        self._jerk = [0.0] * (n - 1)
        self._gap: list[float] = [0.0] * (n - 1)
        self._desired: list[float] = [0.0] * (n - 1)
        self._collided: list[bool] = [False] * (n - 1)
        self._rx: list[int] = [0] * n
        self._lost: list[int] = [0] * n
        self._estopped: list[bool] = [False] * n
        self._failed: list[bool] = [False] * n  # a refused action stopped it for the episode
        self._policy_errors: list[int] = [0] * n
        self._frames: list[Frame] = []
        self._faults_seen: set[Fault] = set()
        self._muted = {f.vehicle for f in self.faults if f.mutes}
        self.safety_events: list[tuple[float, int, str]] = []
        """(t s, vehicle, reason): faults injected and emergency stops, in order."""

    def _tick(self) -> dict[str, np.ndarray]:
        """Own states -> Tx -> channel -> Rx -> observations, at ``self.t``."""
        p = self.plant
        t = self.t
        truth = (p.x.tolist(), p.y.tolist(), p.speed.tolist(), p.heading.tolist(),
                 p.accel.tolist(), p.yaw_rate.tolist())
        self._truth = truth
        xs, ys, vs, hs, acs, yrs = truth
        if self.gps_noise_m > 0.0:
            noise = self._gps_rng.normal(0.0, self.gps_noise_m, size=(2, self.n_vehicles))
            xs = (p.x + noise[0]).tolist()
            ys = (p.y + noise[1]).tolist()
        members = self.members
        channel = self.channel
        lengths, widths = self._lengths, self._widths
        for i, m in enumerate(members):
            st = VehicleState(i, t, xs[i], ys[i], vs[i], hs[i], acs[i], yrs[i], lengths[i], widths[i])
            muted = bool(self._muted) and i in self._muted and self._fault_active(i, t, mutes=True)
            sent = member_tick.begin(m, st, t, may_send=not muted)
            if sent is not None:
                channel.send(i, sent, t)
        inboxes: list[list[VehicleState]] = [[] for _ in members]
        for r, _, msg in channel.deliver(t):
            inboxes[r].append(msg)
        if self._forged:
            self._forge(t, inboxes)
        self._frames = [member_tick.sense(m, box, t) for m, box in zip(members, inboxes)]
        return {a: self._frames[i].observation for i, a in enumerate(self.agents, start=1)}

    def _forge(self, t: float, inboxes: list[list[VehicleState]]) -> None:
        """The forgers' broadcasts this tick: one forged state per active ``forge`` fault,
        offered to every other member (verified when ``auth``)."""
        x, y, v, h = self._truth[:4]
        claimed = []
        for f in self._forged:
            if f.active(t):
                i = f.vehicle
                claimed.append(VehicleState(i, t, x[i], y[i], v[i], h[i], 0.0, 0.0,
                                            self._lengths[i], self._widths[i]))
        self.auth.deliver_forgeries(claimed, inboxes)

    @property
    def forged_rejected(self) -> list[int]:
        """Forged messages each member rejected so far (``forge`` faults, ``auth`` on)."""
        return list(self.auth.rejected)

    def _measure(self) -> None:
        """Ground-truth gaps, desired gaps, collisions and message counters at ``self.t``."""
        x, y = self._truth[0], self._truth[1]
        hypot = math.hypot
        self._gap = [hypot(x[i - 1] - x[i], y[i - 1] - y[i]) for i in range(1, len(x))]
        self._desired = [f.desired_gap_m for f in self._frames[1:]]
        self._collided = [g < h for g, h in zip(self._gap, self._half_sum)]
        self._rx = self.channel.delivered_to
        self._lost = self.channel.lost_to

    def _fault_active(self, i: int, t: float, mutes: bool = False, brakes: bool = False) -> bool:
        return any(
            f.vehicle == i and f.active(t) and ((mutes and f.mutes) or (brakes and f.brakes))
            for f in self.faults
        )

    def _apply_faults(self, t: float) -> None:
        """Faulty vehicles brake to rest at their limit (speed setpoint 0, heading held)."""
        for f in self.faults:
            if not f.active(t):
                continue
            if f not in self._faults_seen:
                self._faults_seen.add(f)
                self.safety_events.append((t, f.vehicle, f"fault {f}"))
            if f.brakes:
                self._cmd_speed[f.vehicle] = 0.0
                self._cmd_dh[f.vehicle] = 0.0
                self._modes[f.vehicle] = "stop"

    def _policy_error(self, i: int, t: float, why: str) -> None:
        """A refused action: counted; the follower stops for the rest of the episode (the
        vehicle's policy-error failsafe)."""
        self._policy_errors[i] += 1
        if not self._failed[i]:
            self._failed[i] = True
            self.safety_events.append((t, i, f"policy error: {why}"))

    def _emergency(self, i: int, t: float, reading: tuple[float, float] | None) -> bool:
        """The braking-aware gap rule for follower ``i`` (latched once it fires)."""
        if self._estopped[i]:
            return True
        rule = self._braking[i]
        assert rule is not None
        if reading is not None:
            gap, closing = reading[0], -reading[1]
        else:
            est = self.members[i].gap_estimate(t)
            if est is None:
                return False
            gap, closing = est
        bumper = bumper_gap(gap, self._lengths[i], self._lengths[i - 1])
        if not rule.too_close(bumper, closing):
            return False
        self._estopped[i] = True
        self.safety_events.append((t, i, "emergency stop: " + rule.reason(bumper, closing)))
        return True

    def _ranging_readings(self) -> dict[int, tuple[float, float]]:
        """Range (m) and range rate (m/s) to the vehicle ahead for vehicles with a sensor."""
        out: dict[int, tuple[float, float]] = {}
        if not self._ranging:
            return out
        p = self.plant
        for i, sensor in self._ranging:
            dx, dy = p.x[i - 1] - p.x[i], p.y[i - 1] - p.y[i]
            rng_m = math.hypot(dx, dy)
            if rng_m > sensor.max_range_m or rng_m <= 0.0:
                continue
            dvx = p.speed[i - 1] * math.cos(p.heading[i - 1]) - p.speed[i] * math.cos(p.heading[i])
            dvy = p.speed[i - 1] * math.sin(p.heading[i - 1]) - p.speed[i] * math.sin(p.heading[i])
            rate = (dx * dvx + dy * dvy) / rng_m
            n1, n2 = self._ranging_rng.normal(size=2)
            out[i] = (rng_m + sensor.range_noise_m * n1, rate + sensor.range_rate_noise_mps * n2)
        return out

    def _infos(self) -> dict[str, dict[str, Any]]:
        speed, accel = self._truth[2], self._truth[4]
        leader_speed = speed[0]
        gap, desired = self._gap, self._desired
        if self._row_inputs is None:  # right after reset: nothing applied yet
            cmd_v = cmd_dh = [math.nan] * self.n_vehicles
        else:
            cmd_v, cmd_dh = self._row_inputs[2], self._row_inputs[3]
        rx, lost = self._rx, self._lost
        collided = self._collided
        out = {}
        for i, a in enumerate(self.agents, start=1):
            m, f = self.members[i], self._frames[i]
            out[a] = {
                "t_s": self.t,
                "gap_m": gap[i - 1],
                "desired_gap_m": _opt(desired[i - 1]),
                "platooning_error_m": _opt(abs(gap[i - 1] - desired[i - 1])),
                "spacing_error_m": _opt(f.spacing_error_m),
                "speed_mps": speed[i],
                "accel_mps2": accel[i],
                "leader_speed_mps": leader_speed,
                "cmd_speed_mps": _opt(cmd_v[i]),
                "cmd_heading_change_rad": _opt(cmd_dh[i]),
                "mode": self._modes[i],
                "collision": collided[i - 1],
                "msgs_sent": m.msgs_sent,
                "msgs_received": rx[i],
                "msgs_kept": m.msgs_received,
                "msgs_lost": lost[i],
                "pred_msg_age_s": _opt(f.pred_msg_age_s),
                "policy_errors": self._policy_errors[i],
            }
        return out


def convoy_aec_env(**kwargs: Any):
    """The AEC version of ``ConvoyEnv(**kwargs)`` via PettingZoo's ``parallel_to_aec``."""
    return parallel_to_aec(ConvoyEnv(**kwargs))
