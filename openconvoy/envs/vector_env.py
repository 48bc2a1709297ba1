"""VectorConvoyEnv: ``num_envs`` convoys stepped together as struct-of-arrays.

The same tick as ``ConvoyEnv`` (plant, channel, Tx and Rx gates, R^i buffers and trails,
staleness ladder, observation layout v1, braking-aware emergency stop, faults, reward)
over every convoy and vehicle at once, in compiled kernels (numba, the ``batched``
extra; ``vector_jit``): one call per stage, no Python loop over vehicles or convoys in
the step. Convoy ``b`` reset with seed ``s`` reproduces ``ConvoyEnv.reset(seed=s)`` for
the same actions: the same deliveries (counter-based draws, ``comms.loss``), modes and
terminations, and states within float rounding (``tests/envs/test_vector_env.py``).

The parts: ``vector_links`` (which links a topology keeps, index tables),
``vector_plant``, ``vector_leader``, ``vector_channel`` (Tx gates, loss, latency),
``vector_rx`` (R^i buffers) and ``vector_trail``, ``vector_member`` (estimate, ladder,
emergency stop), ``vector_obs``, ``vector_measures`` (gaps, reward, infos).
Per-vehicle work follows the kept links, so a ``lookahead:K`` convoy costs O(N·K); loss
is drawn on every ordered pair (``link_counters="all"``, ``ConvoyEnv``'s counters) or
on the kept links only.

Arrays: observations ``(B, N-1, D)`` float32 (followers in order), actions
``(B, N-1, 2)``; rewards ``(B, N-1)``; ``terminated``/``truncated`` ``(B,)``. Not yet
supported (a ConfigError says so): GPS noise, ranging sensors, ``forge`` faults,
latency jitter, traffic scenarios.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from openconvoy.comms.loss import LossConfig
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_faults, parse_fault
from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import ObservationLayout
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.core.safety import for_vehicle
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.scenarios import PathScenario, make_scenario
from openconvoy.envs.vector_channel import VectorChannel
from openconvoy.envs.vector_leader import LeaderDriver
from openconvoy.envs.vector_links import build_links
from openconvoy.envs.vector_measures import infos, measure, pack_reward, reward
from openconvoy.envs.vector_member import COOP, FAILSAFE, STOP, decide, pack_ladder, pack_spacing
from openconvoy.envs.vector_obs import observe, pack_layout
from openconvoy.envs.vector_plant import VectorPlant
from openconvoy.envs.vector_rx import RxBuffers
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset

MODES = ("coop", "degraded", "stop", "failsafe")
"""Mode names by code in the mode arrays (``MODES[code]`` is the log's name)."""
__all__ = ["COOP", "FAILSAFE", "MODES", "STOP", "VectorConvoyEnv"]


def _per_convoy_loss(loss: LossConfig | Sequence[LossConfig] | None, B: int) -> list[LossConfig]:
    """One LossConfig per convoy; a sequence may differ only in ``per`` (a batched sweep)."""
    if loss is None or isinstance(loss, LossConfig):
        return [loss or LossConfig()] * B
    out = list(loss)
    if len(out) != B:
        raise ConfigError(f"loss: need one LossConfig per convoy ({B}), got {len(out)}")
    same = lambda c: (c.model, c.mean_burst_s, c.latency_s, c.jitter_s)  # noqa: E731
    if any(same(c) != same(out[0]) for c in out[1:]):
        raise ConfigError("loss: the convoys' LossConfigs may differ only in per")
    return out


def _check_args(
    num_envs: int, control_rate_hz: float, gps_noise_m: float, render_mode: str | None
) -> None:
    if num_envs < 1:
        raise ConfigError(f"num_envs must be at least 1, got {num_envs}")
    if control_rate_hz <= 0:
        raise ConfigError(f"control_rate_hz must be positive, got {control_rate_hz}")
    if gps_noise_m != 0.0:
        raise ConfigError("VectorConvoyEnv does not support gps_noise_m yet (use ConvoyEnv)")
    if render_mode is not None:
        raise ConfigError("VectorConvoyEnv does not render (use ConvoyEnv)")


def _scenario(
    scenario: str | PathScenario,
    n_followers: int | None,
    vehicle_presets: Sequence[VehiclePreset | str] | None,
) -> PathScenario:
    presets = None
    if vehicle_presets is not None:
        presets = [
            p if isinstance(p, VehiclePreset) else vehicle_preset(p) for p in vehicle_presets
        ]
    built = make_scenario(scenario, n_followers, presets) if isinstance(scenario, str) else scenario
    if not isinstance(built, PathScenario):
        raise ConfigError(
            "VectorConvoyEnv supports path scenarios (paper, track, emergency-braking, track-file)"
        )
    if built.n_vehicles < 2:
        raise ConfigError("a convoy needs a leader and at least one follower")
    if any(p.ranging for p in built.presets[1:]):
        raise ConfigError("VectorConvoyEnv does not model ranging sensors yet (use ConvoyEnv)")
    return built


class VectorConvoyEnv:
    """``num_envs`` convoys of a scenario-driven leader and ``n`` followers, batched.

    Arguments after ``num_envs`` are ``ConvoyEnv``'s (see there); ``reset(seed=s)`` seeds
    convoy ``b`` with ``s + b`` (or ``seed`` may be a sequence of B seeds).
    ``autoreset``: a convoy whose episode ended is reset within the same ``step``
    (its seed sequence continued, as ``ConvoyEnv.reset()`` without a seed) and the
    observation returned is the new episode's first; the final one is in
    ``infos["final_observation"]``.
    ``link_counters``: ``"all"`` (default) draws loss on every ordered pair, as
    ``ConvoyEnv``, so the message counters match it; ``"kept"`` only on the links the
    topology keeps (the same deliveries into R^i, hence the same run; counters then
    count those links): O(N·K) per step for ``lookahead:K``.
    """

    def __init__(
        self,
        num_envs: int,
        scenario: str | PathScenario = "paper",
        n_followers: int | None = None,
        member_config: MemberConfig | None = None,
        loss: LossConfig | Sequence[LossConfig] | None = None,
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
        autoreset: bool = True,
        link_counters: str = "all",
    ) -> None:
        _check_args(num_envs, control_rate_hz, gps_noise_m, render_mode)
        self.scenario = sc = _scenario(scenario, n_followers, vehicle_presets)
        self.num_envs = B = int(num_envs)
        self.n_vehicles = N = sc.n_vehicles
        self.losses = _per_convoy_loss(loss, B)
        self.loss = max(self.losses, key=lambda c: c.per)
        self._check_loss(link_counters)
        self.faults = tuple(f if isinstance(f, Fault) else parse_fault(f) for f in faults)
        if any(f.forges for f in self.faults):
            raise ConfigError("VectorConvoyEnv does not model forge faults (use ConvoyEnv)")
        check_faults(self.faults, N)
        self.presets = tuple(sc.presets)
        self.autoreset, self.link_counters, self.render_mode = autoreset, link_counters, None
        self.control_rate_hz = float(control_rate_hz)
        self.dt = 1.0 / self.control_rate_hz
        self.max_time_s = float(sc.duration_s if max_time_s is None else max_time_s)
        self.max_steps = max(1, int(round(self.max_time_s / self.dt)))
        self.reward_config = reward_config or RewardConfig()
        self.member_config = mc = member_config or MemberConfig(spacing=sc.spacing)
        self.layout: ObservationLayout = mc.layout
        self.emergency_stop = bool(emergency_stop)
        self.possible_agents = [f"follower_{i}" for i in range(1, N)]
        self._constants(gap_margin_m)
        self.links = build_links(mc, N)
        self.L = self.links.L
        self.plant = VectorPlant(list(self.presets) * B, self.dt)
        self.leader = LeaderDriver(sc, B)
        self.channel = VectorChannel(
            B, self.links, self.losses, mc.trigger, self.faults, self.dt, link_counters == "all"
        )
        self.rx = RxBuffers(B, self.L, mc.k, mc.trail_spacing_m)
        self._seed_seqs: list[np.random.SeedSequence | None] = [None] * B
        self.t: np.ndarray = np.zeros(B)
        self.step_count = np.zeros(B, dtype=np.int64)
        self._alloc()

    def _check_loss(self, link_counters: str) -> None:
        if self.loss.jitter_s > 0.0:
            raise ConfigError("VectorConvoyEnv does not support latency jitter yet (use ConvoyEnv)")
        if link_counters not in ("all", "kept"):
            raise ConfigError(f"link_counters must be 'all' or 'kept', got {link_counters!r}")
        if link_counters == "kept" and (
            self.loss.latency_s > 0.0 or (self.loss.per > 0.0 and self.loss.model != "bernoulli")
        ):
            raise ConfigError("link_counters='kept' supports instant Bernoulli links only")

    def _constants(self, gap_margin_m: float | None) -> None:
        """The kernels' per-vehicle constants and packed configs."""
        P, mc = self.presets, self.member_config
        self.lengths = np.array([p.length_m for p in P])
        self._half_sum = 0.5 * (self.lengths[1:] + self.lengths[:-1])
        decel = np.array([p.decel_max_mps2 for p in P], dtype=float)
        self._decel = np.where(decel > 0.0, decel, np.inf)
        rules = [
            for_vehicle(p.decel_max_mps2, p.actuation_delay_s, p.speed_lag_s, p.length_m, gap_margin_m)
            for p in P[1:]
        ]  # fmt: skip
        self._rule = np.array([[r.decel_mps2, r.reaction_s, r.margin_m] for r in rules]).T.copy()
        f32 = np.float32
        self.action_low = np.array([[0.0, float(f32(-MAX_HEADING_CHANGE_RAD))]] * (len(P) - 1))
        self.action_high = np.array(
            [[float(f32(p.max_speed_mps)), float(f32(MAX_HEADING_CHANGE_RAD))] for p in P[1:]]
        )
        self._spacing = pack_spacing(mc.spacing)
        self._ladder = pack_ladder(mc.ladder)
        self._geom = pack_layout(mc.layout)
        self._reward_c = pack_reward(self.reward_config)
        self._brakes = [(f.vehicle, f.t_s - 1e-9) for f in self.faults if f.brakes]

    def _alloc(self) -> None:
        B, N = self.num_envs, self.n_vehicles
        self._link_decel = self._decel[self.links.link_s] if self.L else np.ones(1)
        self.modes = np.zeros((B, N), dtype=np.int64)
        self.cmd_v = np.zeros((B, N))
        self.cmd_dh = np.zeros((B, N))
        self.estopped = np.zeros((B, N), dtype=bool)
        self.policy_failed = np.zeros((B, N), dtype=bool)
        self.policy_errors = np.zeros((B, N), dtype=np.int64)
        self.desired_gap = np.full((B, N), np.nan)
        self.spacing_error = np.full((B, N), np.nan)
        self.pred_age = np.full((B, N), np.nan)
        self.pred_est = np.full((2, B, N), np.nan)  # arc to head, closing
        self._has_cmd = np.zeros(B, dtype=bool)
        self._own = self.plant.state.reshape(6, B, N)  # views, for the kernels
        self._cmd_v_flat, self._cmd_dh_flat = self.cmd_v.reshape(-1), self.cmd_dh.reshape(-1)
        self._everyone = np.ones(B, dtype=bool)
        self._fresh_age_s = self.member_config.fresh_age_s
        self.gap = np.zeros((B, N - 1))
        self.collided = np.zeros((B, N - 1), dtype=bool)

    # --- API ------------------------------------------------------------------------

    @property
    def own(self) -> np.ndarray:
        """The plant state (6, B, N): x, y, speed, heading, accel, yaw rate (a view)."""
        return self._own

    @property
    def own_truth(self) -> tuple[np.ndarray, ...]:
        """x, y, speed, heading, accel, yaw rate, each (B, N), a snapshot."""
        return tuple(self.own.copy())

    def reset(self, seed: int | Sequence[int] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every convoy: convoy ``b`` gets ``seed + b`` (or ``seed[b]``)."""
        B = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * B
        elif isinstance(seed, (int, np.integer)):
            seeds = [int(seed) + b for b in range(B)]
        else:
            seeds = [int(s) for s in seed]
            if len(seeds) != B:
                raise ConfigError(f"reset needs {B} seeds, got {len(seeds)}")
        which = np.ones(B, dtype=bool)
        self._reset_convoys(which, seeds)
        obs = np.empty((B, self.n_vehicles - 1, self.layout.size), dtype=np.float32)
        self._tick(which, obs)
        measure(self.own, self._half_sum, self.gap, self.collided)
        return obs, infos(self)

    def _reset_convoys(self, which: np.ndarray, seeds: Sequence[int | None]) -> None:
        # Per-convoy seeding: a loop over the convoys being reset (episode starts only).
        for b in np.flatnonzero(which).tolist():
            s = seeds[b]
            if s is not None:
                self._seed_seqs[b] = np.random.SeedSequence(s)
            elif self._seed_seqs[b] is None:
                self._seed_seqs[b] = np.random.SeedSequence()
            seq = self._seed_seqs[b]
            assert seq is not None
            self.channel.seed(b, np.random.default_rng(seq.spawn(4)[0]))
        init = self.scenario.initial_state()
        N, n = self.n_vehicles, int(which.sum())
        rows = np.flatnonzero(np.repeat(which, N))
        tile = lambda a: np.tile(np.asarray(a, dtype=float), n)  # noqa: E731
        self.plant.reset_rows(
            rows, tile(init.x), tile(init.y), tile(init.heading), tile(init.speed)
        )
        self.leader.reset(which)
        self.channel.reset(which)
        self.rx.reset(which)
        self.t[which] = 0.0
        self.step_count[which] = 0
        for arr, value in (
            (self.modes, COOP), (self.cmd_v, 0.0), (self.cmd_dh, 0.0), (self.estopped, False),
            (self.policy_failed, False), (self.policy_errors, 0), (self._has_cmd, False),
        ):  # fmt: skip
            arr[which] = value

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One tick of every convoy with ``actions`` ``(B, N-1, 2)`` (SI, clipped)."""
        B, N = self.num_envs, self.n_vehicles
        a = np.asarray(actions, dtype=np.float32)
        if a.shape != (B, N - 1, 2):
            raise ValueError(f"actions must have shape {(B, N - 1, 2)}, got {a.shape}")
        accel_old = self._command(a)
        self.step_count += 1
        self.t = self.step_count * self.dt
        obs = np.empty((B, N - 1, self.layout.size), dtype=np.float32)
        self._tick(self._everyone, obs)
        own = self.own
        measure(own, self._half_sum, self.gap, self.collided)
        rewards = np.empty((B, N - 1))
        reward(self.gap, self.desired_gap, accel_old, own, self.collided, 1.0 / self.dt,
               self._reward_c, rewards)  # fmt: skip
        terminated = np.asarray(self.collided.any(axis=1))
        truncated = (self.step_count >= self.max_steps) & ~terminated
        info = infos(self)
        done = terminated | truncated
        if self.autoreset and done.any():
            info["final_observation"] = obs.copy()
            self._reset_convoys(done, [None] * B)
            self._tick(done, obs)
            measure(self.own, self._half_sum, self.gap, self.collided)
        return obs, rewards, terminated, truncated, info

    def _command(self, a: np.ndarray) -> np.ndarray:
        """The members decide, the leaders drive, faults act, the plant moves ``dt``;
        returns the accelerations before the move (B, N)."""
        t, own, lk, rx = self.t, self.own, self.links, self.rx
        decide(
            a, self.action_low, self.action_high, t, own, rx.hist, rx.hist_n, lk.needed,
            lk.pred_link, self._link_decel, self.lengths, self._spacing, self._ladder,
            self._fresh_age_s, MAX_HEADING_CHANGE_RAD, self.pred_est,
            self.policy_errors, self.policy_failed, self.estopped, self.emergency_stop,
            self._rule, self.cmd_v, self.cmd_dh, self.modes,
        )  # fmt: skip
        self.leader.command(t, own, self.cmd_v, self.cmd_dh)
        for vehicle, t_from in self._brakes:
            on = t >= t_from
            self.cmd_v[on, vehicle] = 0.0
            self.cmd_dh[on, vehicle] = 0.0
            self.modes[on, vehicle] = STOP
        self._has_cmd[:] = True
        accel_old = own[4].copy()
        self.plant.step(self._cmd_v_flat, self._cmd_dh_flat)
        return accel_old

<<<<<<< HEAD
    def _tick(self, which: np.ndarray, obs: np.ndarray) -> None:
        """Own states -> Tx -> channel -> Rx -> observations ``obs`` at ``self.t``, for
        the convoys ``which``."""
        own, lk, rx = self.own, self.links, self.rx
        self.channel.transmit(self.t, self.step_count, own, which, rx)
        observe(
            obs, which, self.t, own, rx.hist, rx.hist_n, rx.trail, rx.trail_n, rx.hint, rx.hint_k,
            lk.slot_link, lk.target_link, lk.pred_link, self._link_decel, self.lengths,
            self._spacing, self.member_config.ladder.stop_after_s,
            self._fresh_age_s, self._geom, self.desired_gap, self.spacing_error,
            self.pred_age, self.pred_est,
        )  # fmt: skip
=======
    @property
    def own_truth(self) -> tuple[np.ndarray, ...]:
        return tuple(self.own)

    def _supervise(self, a0: np.ndarray, a1: np.ndarray, t: np.ndarray):
        """``ConvoyMember.supervise`` for every follower (no ranging sensors)."""
        lad: LadderConfig = self.member_config.ladder
        age = self._needed_age(t)[:, 1:]
        if lad.enabled:
            mode = np.where(
                age <= lad.degrade_after_s, COOP, np.where(age <= lad.stop_after_s, DEGRADED, STOP)
            )
        else:
            mode = np.zeros_like(a0, dtype=np.int64)
        v, dh = a0.copy(), a1.copy()
        if lad.enabled:
            est_gap, est_closing = self.pred_est[0][:, 1:], self.pred_est[1][:, 1:]
            have = ~np.isnan(est_gap)
            ego_v = self.own[2][:, 1:]
            desired = self._pair_gap(ego_v)
            target_gap = desired + lad.extra_headway_s * np.maximum(ego_v, 0.0)
            acc_v = np.maximum(0.0, ego_v + est_closing + lad.gap_gain * (est_gap - target_gap))
            deg = mode == DEGRADED
            ok = deg & have
            f32 = lambda x: x.astype(np.float32).astype(np.float64)  # noqa: E731
            v = np.where(ok, f32(np.minimum(a0, acc_v)), v)
            dh = np.where(ok, f32(np.clip(a1, -MAX_HEADING_CHANGE_RAD, MAX_HEADING_CHANGE_RAD)), dh)
            mode = np.where(deg & ~have, STOP, mode)
            stop = mode == STOP
            v = np.where(stop, 0.0, v)
            dh = np.where(stop, 0.0, dh)
        return v, dh, mode

    def _needed_age(self, t: np.ndarray) -> np.ndarray:
        """Age of the oldest newest message among the needed vehicles, (B, N)."""
        age = self._link_age(t)
        padded = np.concatenate([age, np.zeros((self.num_envs, 1))], axis=1)
        return padded[:, self._needed].max(axis=2)

    def _link_age(self, t: np.ndarray) -> np.ndarray:
        heard = self.hist_n > 0
        return np.where(heard, np.maximum(0.0, t[:, None] - self.hist[0, :, :, 0]), np.inf)

    def _pair_gap(self, speed: np.ndarray, ego: slice = slice(1, None)) -> np.ndarray:
        """Desired centre-to-centre gap to the immediate predecessor at ``speed`` (B, N-1)."""
        c = self.member_config.spacing
        if c.kind == "constant-distance":
            return np.full(speed.shape, c.distance_m)
        v = np.maximum(speed, 0.0)
        gap = c.standstill_m + c.headway_s * v
        if c.kind == "quadratic":
            gap = gap + c.quadratic_s2_per_m * v * v
        return gap + 0.5 * (self.lengths[1:] + self.lengths[:-1])

    def _estimate(self, link: np.ndarray, t: np.ndarray):
        """``ConvoyMember.estimate`` of each link's sender, shapes (B, *link.shape)."""
        mc = self.member_config
        lad = mc.ladder
        li = np.where(link >= 0, link, 0)
        tt = t.reshape((-1,) + (1,) * link.ndim)
        n = self.hist_n[:, li]
        lt, lx, ly, lv, lh = (self.hist[f][:, li, 0] for f in range(5))
        age = np.maximum(tt - lt, 0.0)
        valid = (link >= 0) & (n > 0) & ~(age > lad.stop_after_s)
        fresh = age <= mc.fresh_age_s
        a = self._decel[self._link_s[li]]
        moving = (lv > 0.0) & ~np.isinf(a)
        with np.errstate(divide="ignore", invalid="ignore"):
            tau = np.minimum(age, lv / a)
            d_stale = np.where(moving, lv * tau - 0.5 * a * tau * tau, 0.0)
            v_stale = np.where(moving, np.maximum(lv - a * age, 0.0), 0.0)
        d = np.where(fresh, lv * age, d_stale)
        speed = np.where(fresh, lv, v_stale)
        return valid, lx + d * np.cos(lh), ly + d * np.sin(lh), speed, lh, age

    def _emergency(self, t: np.ndarray) -> None:
        """The braking-aware gap rule on each follower's estimate of its predecessor."""
        valid, ex, ey, es, eh, _ = self._estimate(self._pred_link, t)
        ox, oy, ov, oh = (
            self.own[0][:, 1:],
            self.own[1][:, 1:],
            self.own[2][:, 1:],
            self.own[3][:, 1:],
        )
        dx, dy = ex - ox, ey - oy
        gap = np.hypot(dx, dy)
        vx = ov * np.cos(oh) - es * np.cos(eh)
        vy = ov * np.sin(oh) - es * np.sin(eh)
        with np.errstate(divide="ignore", invalid="ignore"):
            closing = np.where(gap <= 0.0, np.maximum(ov - es, 0.0), (dx * vx + dy * vy) / gap)
        gap = np.where(gap <= 0.0, 0.0, gap)
        bumper = gap - 0.5 * (self.lengths[1:] + self.lengths[:-1])
        closing = np.where(np.isfinite(closing), closing, 0.0)
        stopping = np.where(
            closing > 0.0,
            closing * closing / (2.0 * self._rule_decel) + self._rule_reaction * closing,
            0.0,
        )
        fire = valid & np.isfinite(bumper) & (bumper - stopping < self._rule_margin)
        fire = fire | self.estopped[:, 1:]
        self.estopped[:, 1:] = fire
        self.cmd_v[:, 1:] = np.where(fire, 0.0, self.cmd_v[:, 1:])
        self.cmd_dh[:, 1:] = np.where(fire, 0.0, self.cmd_dh[:, 1:])
        self.modes[:, 1:] = np.where(fire, FAILSAFE, self.modes[:, 1:])

    def _apply_faults(self, t: np.ndarray) -> None:
        for f in self.faults:
            if f.brakes:
                on = t >= f.t_s - 1e-9
                self.cmd_v[on, f.vehicle] = 0.0
                self.cmd_dh[on, f.vehicle] = 0.0
                self.modes[on, f.vehicle] = STOP

    def _muted(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros((self.num_envs, self.n_vehicles), dtype=bool)
        for f in self.faults:
            if f.mutes:
                out[:, f.vehicle] |= t >= f.t_s - 1e-9
        return out

    def _tx(self, t: np.ndarray, which: np.ndarray) -> np.ndarray:
        """τ for every vehicle: who broadcasts now (and the gate's check grid)."""
        trig = self.member_config.trigger
        tt = t[:, None]
        nc = self.next_check
        due = which[:, None] & ~(tt + 1e-9 < nc) & ~self._muted(t)
        nc[:] = np.where(due & np.isneginf(nc), tt, nc)
        adv = due & (nc <= tt + 1e-9)
        while adv.any():
            nc[adv] += trig.period_s
            adv &= nc <= tt + 1e-9
        if trig.kind == "periodic":
            send = due
        else:
            lt, lx, ly, lv, lh = self.last_sent
            ox, oy, ov = self.own[0], self.own[1], self.own[2]
            dt = tt - lt
            px = lx + lv * np.cos(lh) * dt
            py = ly + lv * np.sin(lh) * dt
            silent = np.isnan(lt) | (tt - lt >= trig.max_silence_s - 1e-9)
            moved = (np.hypot(ox - px, oy - py) > trig.threshold_m) | (
                np.abs(ov - lv) > trig.speed_threshold_mps
            )
            send = due & (silent | moved)
        self.last_sent[0] = np.where(send, tt, self.last_sent[0])
        for f, src in ((1, 0), (2, 1), (3, 2), (4, 3)):
            self.last_sent[f] = np.where(send, self.own[src], self.last_sent[f])
        self.msgs_sent += send
        return send

    def _tick(self, which: np.ndarray) -> np.ndarray:
        """Own states -> Tx -> channel -> Rx -> observations at ``self.t`` (rows ``which``)."""
        B, N = self.num_envs, self.n_vehicles
        p = self.plant
        shape = (B, N)
        own = np.stack(
            [
                p.x.reshape(shape),
                p.y.reshape(shape),
                p.speed.reshape(shape),
                p.heading.reshape(shape),
                p.accel.reshape(shape),
                p.yaw_rate.reshape(shape),
            ]
        )
        self.own = own
        t = self.t
        send = self._tx(t, which)
        self._channel(send, t, which)
        return self._observe(t)

    def _channel(self, send: np.ndarray, t: np.ndarray, which: np.ndarray) -> None:
        """Loss draws for every receiver of every broadcast; deliveries into R^i."""
        B, N = self.num_envs, self.n_vehicles
        per = self.loss.per
        number = self.broadcasts.copy()
        self.broadcasts += send
        if self.link_counters == "kept":
            self._channel_kept(send, t, number)
            return
        if self._ge is not None:
            lost = self._ge_lost(send, t)
        elif per > 0.0:
            s_idx = np.arange(N)[None, :, None]
            r_idx = np.arange(N)[None, None, :]
            u = counter_uniform_array(
                self.keys[:, None, None], s_idx, r_idx, number[:, :, None], DRAW_LOSS
            )
            lost = u < self._per[:, None, None]
        else:
            lost = np.zeros((B, N, N), dtype=bool)
        offdiag = ~np.eye(N, dtype=bool)
        lost &= send[:, :, None] & offdiag
        self.lost_to += lost.sum(axis=1)
        if self._instant:
            arrived = send[:, :, None] & ~lost & offdiag
            self.delivered_to += arrived.sum(axis=1)
            self._push(arrived[:, self._link_s, self._link_r], self.own, t)
            return
        S = self._slots
        rows = np.flatnonzero(which)
        slot = self.step_count[rows] % S
        self.q_arrival[slot, rows] = np.where(
            send[rows], t[rows, None] + self.loss.latency_s, np.inf
        )
        self.q_state[slot, :, rows] = self.own[:, rows].transpose(1, 0, 2)
        self.q_t[slot, rows] = t[rows, None]
        self.q_lost[slot, rows] = lost[rows]
        rows = np.arange(B)
        due_t = t[:, None] + 1e-9
        for back in range(S - 1, -1, -1):
            sl = (self.step_count - back) % S
            arr = self.q_arrival[sl, rows]
            due = arr <= due_t
            if not due.any():
                continue
            arrived = due[:, :, None] & ~self.q_lost[sl, rows] & offdiag
            self.delivered_to += arrived.sum(axis=1)
            self.q_arrival[sl, rows] = np.where(due, np.inf, arr)
            self._push(
                arrived[:, self._link_s, self._link_r],
                self.q_state[sl, :, rows].transpose(1, 0, 2),
                self.q_t[sl, rows],
            )

    def _channel_kept(self, send: np.ndarray, t: np.ndarray, number: np.ndarray) -> None:
        """The channel on the kept links only (``link_counters="kept"``, instant links):
        the same draws on those links, so R^i, modes and states are as with every link;
        the message counters then count kept links only."""
        ls, lr = self._link_s, self._link_r
        offered = send[:, ls]
        if self.loss.per > 0.0:
            u = counter_uniform_array(
                self.keys[:, None], ls[None], lr[None], number[:, ls], DRAW_LOSS
            )
            lost = offered & (u < self._per[:, None])
        else:
            lost = np.zeros_like(offered)
        got = offered & ~lost
        self.lost_to += self._per_receiver(lost)
        self.delivered_to += self._per_receiver(got)
        self._push(got, self.own, t)

    def _push(self, got: np.ndarray, state: np.ndarray, t_sent: np.ndarray) -> None:
        """``StateBuffer.push`` + ``Trail.add`` on every kept link that got a message
        (``got``: (B, L)); ``t_sent`` per convoy (B,) or per sender (B, N)."""
        if self.L == 0:
            return
        self.msgs_kept += self._per_receiver(got)
        ts = (
            t_sent[:, self._link_s]
            if np.ndim(t_sent) == 2
            else np.broadcast_to(t_sent[:, None], got.shape)
        )
        newer = (self.hist_n == 0) | (ts > self.hist[0, :, :, 0])
        push = got & newer
        if not push.any():
            return
        fields = (ts, *(state[f][:, self._link_s] for f in (0, 1, 2, 3, 4)))
        h = self.hist
        h[:, :, :, 1:] = np.where(push[None, :, :, None], h[:, :, :, :-1], h[:, :, :, 1:])
        for f, val in enumerate(fields):
            h[f, :, :, 0] = np.where(push, val, h[f, :, :, 0])
        self.hist_n = np.where(push, np.minimum(self.hist_n + 1, self.member_config.k), self.hist_n)
        self._trail_add(push, fields[1], fields[2])

    def _per_receiver(self, got: np.ndarray) -> np.ndarray:
        """Per-receiver totals (B, N) of a per-link (B, L) count."""
        B, N = self.num_envs, self.n_vehicles
        flat = (np.arange(B)[:, None] * N + self._link_r[None, :]).ravel()
        return (
            np.bincount(flat, weights=got.ravel(), minlength=B * N).reshape(B, N).astype(np.int64)
        )

    def _trail_add(self, push: np.ndarray, x: np.ndarray, y: np.ndarray) -> None:
        tr, n = self.trail, self.trail_n
        bb, ll = np.nonzero(push)
        if len(bb) == 0:
            return
        nn = n[bb, ll]
        last = np.maximum(nn - 1, 0)
        px, py, ps = tr[0, bb, ll, last], tr[1, bb, ll, last], tr[2, bb, ll, last]
        xs, ys = x[bb, ll], y[bb, ll]
        step = np.where(nn > 0, np.hypot(xs - px, ys - py), 0.0)
        keep = (nn == 0) | ~(step < self.member_config.trail_spacing_m)
        bb, ll, nn, xs, ys, step, ps = (
            bb[keep],
            ll[keep],
            nn[keep],
            xs[keep],
            ys[keep],
            step[keep],
            ps[keep],
        )
        full = nn >= TRAIL_CAPACITY
        if full.any():
            half = TRAIL_CAPACITY // 2
            fb, fl = bb[full], ll[full]
            tr[:, fb, fl, : TRAIL_CAPACITY - half] = tr[:, fb, fl, half:]
            nn = np.where(full, nn - half, nn)
        s_new = np.where(nn > 0, ps + step, 0.0)
        tr[0, bb, ll, nn] = xs
        tr[1, bb, ll, nn] = ys
        tr[2, bb, ll, nn] = s_new
        n[bb, ll] = nn + 1

    # --- observation ------------------------------------------------------------------

    def _observe(self, t: np.ndarray) -> np.ndarray:
        """``ConvoyMember.observation`` for every follower: (B, N-1, D) float32."""
        B, N, lay = self.num_envs, self.n_vehicles, self.layout
        F, k = N - 1, lay.k
        obs = np.zeros((B, F, lay.size))
        ex, ey, ev, eh, ea, eyr = (self.own[f][:, 1:] for f in range(6))
        c, s = np.cos(eh), np.sin(eh)
        # State slots: only the (follower, slot) pairs whose sender the topology keeps.
        pf, ps, pl = self._slot_pairs
        if len(pl):
            hs = self.hist[:, :, pl, :]  # (6, B, P, k)
            valid = np.arange(k) < self.hist_n[:, pl][..., None]  # (B, P, k)
            exp, eyp, ehp = ex[:, pf, None], ey[:, pf, None], eh[:, pf, None]
            cc, ss = c[:, pf, None], s[:, pf, None]
            dx = hs[1] - exp
            dy = hs[2] - eyp
            age = t[:, None, None] - hs[0]
            feats = np.empty(valid.shape + (7,))
            feats[..., 0] = cc * dx + ss * dy
            feats[..., 1] = cc * dy - ss * dx
            feats[..., 2] = _wrap(hs[4] - ehp)
            feats[..., 3] = hs[3]
            feats[..., 4] = hs[5]
            feats[..., 5] = np.minimum(np.maximum(age, 0.0), MAX_AGE_S)
            feats[..., 6] = 1.0
            feats *= valid[..., None]
            obs.reshape(B, -1)[:, self._slot_cols] = feats.reshape(B, -1)
        o = lay.own_offset
        obs[:, :, o], obs[:, :, o + 1], obs[:, :, o + 2] = ev, ea, eyr
        self._fill_targets(obs, t)
        return obs.astype(np.float32)

    def _fill_targets(self, obs: np.ndarray, t: np.ndarray) -> None:
        B, N, lay = self.num_envs, self.n_vehicles, self.layout
        F = N - 1
        ex, ey, ev = self.own[0][:, 1:], self.own[1][:, 1:], self.own[2][:, 1:]
        pair = self._pair_gap(ev)  # (B, F): pair gap of follower i+1 to i
        self.desired_gap[:, 1:] = pair
        page = self._link_age(t)
        pl = self._pred_link
        pred_age = np.where(pl >= 0, page[:, np.where(pl >= 0, pl, 0)], np.inf)
        self.pred_age[:, 1:] = np.where(np.isinf(pred_age), np.nan, pred_age)
        # Desired arc gaps to each target, summed in ConvoyMember's order.
        ntg = len(lay.targets)
        desired = np.zeros((B, F, ntg))
        fidx = np.arange(F)  # follower i = fidx + 1; pair j (j+1 behind j) lives at pair[:, j]
        if self.member_config.spacing.kind == "constant-distance":
            gap_at = lambda j: pair[:, np.clip(j, 0, F - 1)]  # noqa: E731
        else:
            # The pair gap (j+1, j) at the ego's speed: lengths of j+1 and j.
            def gap_at(j: np.ndarray) -> np.ndarray:
                jj = np.clip(j, 0, F - 1)
                c = self.member_config.spacing
                v = np.maximum(ev, 0.0)
                g = c.standstill_m + c.headway_s * v
                if c.kind == "quadratic":
                    g = g + c.quadratic_s2_per_m * v * v
                return g + 0.5 * (self.lengths[jj + 1] + self.lengths[jj])

        for m in range(1, ntg):
            acc = np.zeros((B, F))
            for q in range(m):
                acc = acc + gap_at(fidx + 1 - m + q)
            desired[:, :, m] = acc
        if self.member_config.spacing.kind == "constant-distance":
            # Leader: sum of i pair gaps from vehicle 0 on (a sequential cumulative sum).
            desired[:, :, 0] = np.cumsum(
                np.full((B, F), self.member_config.spacing.distance_m), axis=1
            )
        else:
            c = self.member_config.spacing
            v = np.maximum(ev, 0.0)
            base = c.standstill_m + c.headway_s * v
            if c.kind == "quadratic":
                base = base + c.quadratic_s2_per_m * v * v
            # Each follower i sums pairs 0..i-1 at its own speed, in ConvoyMember's order:
            # O(i) per follower that keeps the leader as a target (O(N²) only when all do).
            halves = 0.5 * (self.lengths[1:] + self.lengths[:-1])
            rows = self._leader_rows
            if len(rows):
                terms = base[:, rows, None] + halves[None, None, : rows.max() + 1]
                mask = np.arange(rows.max() + 1)[None, :] <= rows[:, None]
                sums = np.cumsum(np.where(mask[None], terms, 0.0), axis=2)
                desired[:, rows, 0] = sums[:, np.arange(len(rows)), rows]
        tl = self._target_link  # (F, ntg)
        valid, hx, hy, hv, hh, _ = self._estimate(tl, t)  # (B, F, ntg)
        li = np.where(tl >= 0, tl, 0)
        proj = self._project(li, hx, hy, hh, ex[:, :, None], ey[:, :, None], desired, valid)
        arc, cross, pheading, ps = proj
        upd_b, upd_f, upd_k = np.nonzero(valid)
        self.hint[upd_b, li[upd_f, upd_k]] = ps[upd_b, upd_f, upd_k]
        o0 = lay.derived_offset
        for kk in range(ntg):
            o = o0 + kk * 5
            v = valid[:, :, kk]
            obs[:, :, o] = np.where(v, arc[:, :, kk], 0.0)
            obs[:, :, o + 1] = np.where(v, desired[:, :, kk], 0.0)
            obs[:, :, o + 2] = np.where(v, arc[:, :, kk] - desired[:, :, kk], 0.0)
            obs[:, :, o + 3] = np.where(v, hv[:, :, kk], 0.0)
            obs[:, :, o + 4] = np.where(v, 1.0, 0.0)
        # The nearest heard predecessor: pred_1..pred_M, then the leader.
        order = [*range(1, ntg), 0]
        chosen = np.full((B, F), -1, dtype=np.int64)
        for kk in reversed(order):
            chosen = np.where(valid[:, :, kk], kk, chosen)
        have = chosen >= 0
        ck = np.where(have, chosen, 0)
        bi, fi = np.meshgrid(np.arange(B), np.arange(F), indexing="ij")
        sel_err = (arc - desired)[bi, fi, ck].astype(np.float32).astype(np.float64)
        self.spacing_error[:, 1:] = np.where(have, sel_err, np.nan)
        is_p1 = have & (ck == 1)
        self.pred_est[0][:, 1:] = np.where(is_p1, arc[bi, fi, ck], np.nan)
        self.pred_est[1][:, 1:] = np.where(is_p1, hv[bi, fi, ck] - ev, np.nan)
        self._fill_path(
            obs,
            have,
            li[fi, ck],
            hx[bi, fi, ck],
            hy[bi, fi, ck],
            hh[bi, fi, ck],
            cross[bi, fi, ck],
            pheading[bi, fi, ck],
            ps[bi, fi, ck],
        )

    def _query(self, b, link, hx, hy, hh) -> dict[str, np.ndarray]:
        """Per-query trail data (``Trail`` queries on the path ending at the head
        ``(hx, hy)`` with heading ``hh``): flat offsets, first and last breadcrumbs, the
        head's arc coordinate and the backward direction of the extension."""
        C = TRAIL_CAPACITY
        base = (b * self.L + link) * C
        n = self.trail_n[b, link]
        X, Y, S = (self.trail[f].reshape(-1) for f in range(3))
        x0, y0, s0 = X.take(base), Y.take(base), S.take(base)
        lastc = base + n - 1
        lx, ly, ls = X.take(lastc), Y.take(lastc), S.take(lastc)
        second = base + np.minimum(1, n - 1)
        two = n >= 2
        dx = np.where(two, X.take(second) - x0, hx - x0)
        dy = np.where(two, Y.take(second) - y0, hy - y0)
        d = np.hypot(dx, dy)
        small = d < 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            bx = np.where(small, -np.cos(hh), -dx / d)
            by = np.where(small, -np.sin(hh), -dy / d)
        to_head = np.hypot(hx - lx, hy - ly)
        return {
            "base": base,
            "n": n,
            "X": X,
            "Y": Y,
            "S": S,
            "hx": hx,
            "hy": hy,
            "hh": hh,
            "x0": x0,
            "y0": y0,
            "s0": s0,
            "lx": lx,
            "ly": ly,
            "ls": ls,
            "bx": bx,
            "by": by,
            "to_head": to_head,
            "s_head": ls + to_head,
        }

    @staticmethod
    def _vertex(q: dict[str, np.ndarray], k: np.ndarray):
        """Vertex ``k`` of the query path (``Trail._vertex``): x, y, s."""
        n = q["n"]
        flat = q["base"] + np.clip(k, 0, n - 1)
        cx, cy, cs = q["X"].take(flat), q["Y"].take(flat), q["S"].take(flat)
        far = 1e4
        head, crumb = k >= n, k >= 0
        x = np.where(head, q["hx"], np.where(crumb, cx, q["x0"] + far * q["bx"]))
        y = np.where(head, q["hy"], np.where(crumb, cy, q["y0"] + far * q["by"]))
        s = np.where(head, q["s_head"], np.where(crumb, cs, q["s0"] - far))
        return x, y, s

    def _segment(self, q, k, x, y):
        """``Trail._segment``: (dist², s, cross, heading) of (x, y) on segment k."""
        ax, ay, sa = self._vertex(q, k)
        bx, by, sb = self._vertex(q, k + 1)
        dx, dy = bx - ax, by - ay
        seg = np.hypot(dx, dy)
        degenerate = seg < 1e-12
        rx, ry = x - ax, y - ay
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.minimum(np.maximum((rx * dx + ry * dy) / (seg * seg), 0.0), 1.0)
            ex, ey = rx - u * dx, ry - u * dy
            d2 = np.where(degenerate, rx**2 + ry**2, ex * ex + ey * ey)
            s = np.where(degenerate, sa, sa + u * (sb - sa))
            cross = np.where(degenerate, 0.0, (dx * ry - dy * rx) / seg)
        heading = np.where(degenerate, q["hh"], np.arctan2(dy, dx))
        return d2, s, cross, heading

    @staticmethod
    def _bisect(q, value):
        """``bisect_right`` of ``value`` in each trail's arc coordinates."""
        lo = np.zeros_like(q["n"])
        hi = q["n"].copy()
        S, base = q["S"], q["base"]
        for _ in range(_BISECT_STEPS):
            active = lo < hi
            if not active.any():
                break
            mid = (lo + hi) >> 1
            go_left = value < S.take(base + np.minimum(mid, TRAIL_CAPACITY - 1))
            hi = np.where(active & go_left, mid, hi)
            lo = np.where(active & ~go_left, mid + 1, lo)
        return lo

    def _project(self, li, hx, hy, hh, x, y, expected, valid):
        """``Trail.project`` for every valid (convoy, follower, target) query."""
        shape = valid.shape
        B = shape[0]
        b = np.broadcast_to(np.arange(B).reshape(B, 1, 1), shape)
        link = np.broadcast_to(li[None], shape)
        qb, ql = b[valid], link[valid]
        out = [np.zeros(shape) for _ in range(4)]
        if len(qb) == 0:
            return out
        q = self._query(qb, ql, hx[valid], hy[valid], hh[valid])
        xq, yq = np.broadcast_to(x, shape)[valid], np.broadcast_to(y, shape)[valid]
        n = q["n"]
        last = np.where(q["to_head"] > 1e-9, n - 1, n - 2)
        s_head = q["s_head"]
        hint = self.hint[qb, ql]
        start = np.where(np.isnan(hint), s_head - expected[valid], hint)
        k = np.minimum(np.maximum(self._bisect(q, start) - 1, -1), last)
        best = self._segment(q, k, xq, yq)
        for step in (1, -1):
            j = k + step
            active = (j >= -1) & (j <= last)
            while active.any():
                cand = self._segment(q, j, xq, yq)
                better = active & (cand[0] < best[0])
                best = tuple(np.where(better, c_, b_) for c_, b_ in zip(cand, best))
                k = np.where(better, j, k)
                j = j + step
                active = better & (j >= -1) & (j <= last)
        _, s, cross, heading = best
        for arr, v in zip(out, (s_head - s, cross, heading, s)):
            arr[valid] = v
        return out

    def _point_at(self, q, s):
        """``Trail.point_at``: the path point at arc coordinate ``s``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self._point_at_raw(q, s)

    def _point_at_raw(self, q, s):
        hx, hy, hh = q["hx"], q["hy"], q["hh"]
        lx, ly, ls, s_head = q["lx"], q["ly"], q["ls"], q["s_head"]
        f_head = (s - ls) / (s_head - ls)
        tail_x = lx + f_head * (hx - lx)
        tail_y = ly + f_head * (hy - ly)
        moved = s_head - ls > 1e-9
        ahead_x = np.where(moved, tail_x, hx + (s - s_head) * np.cos(hh))
        ahead_y = np.where(moved, tail_y, hy + (s - s_head) * np.sin(hh))
        s0 = q["s0"]
        back_x = q["x0"] - (s - s0) * q["bx"]
        back_y = q["y0"] - (s - s0) * q["by"]
        n = q["n"]
        i = q["base"] + np.clip(self._bisect(q, s) - 1, 0, np.maximum(n - 2, 0))
        i1 = np.minimum(i + 1, q["base"] + n - 1)
        X, Y, S = q["X"], q["Y"], q["S"]
        xi, yi, si = X.take(i), Y.take(i), S.take(i)
        xj, yj, sj = X.take(i1), Y.take(i1), S.take(i1)
        f = (s - si) / (sj - si)
        mid_x = xi + f * (xj - xi)
        mid_y = yi + f * (yj - yi)
        x = np.where(
            s >= s_head, ahead_x, np.where(s >= ls, tail_x, np.where(s <= s0, back_x, mid_x))
        )
        y = np.where(
            s >= s_head, ahead_y, np.where(s >= ls, tail_y, np.where(s <= s0, back_y, mid_y))
        )
        return x, y

    def _fill_path(self, obs, have, link, hx, hy, hh, cross, pheading, ps) -> None:
        lay = self.layout
        o = lay.path_offset
        if not have.any():
            return
        bb, ff = np.nonzero(have)
        lk = link[bb, ff]
        hxq, hyq, hhq = hx[bb, ff], hy[bb, ff], hh[bb, ff]
        ex, ey, ev, eh = (self.own[f][:, 1:][bb, ff] for f in range(4))
        c, s = np.cos(eh), np.sin(eh)
        obs[bb, ff, o] = -cross[bb, ff]
        obs[bb, ff, o + 1] = _wrap(pheading[bb, ff] - eh)
        scale = np.maximum(1.0, np.abs(ev))
        # The lookahead points of every query in one batch (queries repeated per time).
        nl = len(LOOKAHEAD_S)
        rep = lambda a: np.tile(a, nl)  # noqa: E731
        q = self._query(rep(bb), rep(lk), rep(hxq), rep(hyq), rep(hhq))
        s_look = np.concatenate([ps[bb, ff] + tl * scale for tl in LOOKAHEAD_S])
        px, py = self._point_at(q, s_look)
        P = len(bb)
        dx = (px - rep(ex)).reshape(nl, P)
        dy = (py - rep(ey)).reshape(nl, P)
        for j in range(nl):
            obs[bb, ff, o + 2 + 2 * j] = c * dx[j] + s * dy[j]
            obs[bb, ff, o + 3 + 2 * j] = -s * dx[j] + c * dy[j]
        obs[bb, ff, o + 8] = 1.0

    # --- measures, reward, infos -----------------------------------------------------------

    def _measure(self) -> None:
        x, y = self.own[0], self.own[1]
        self.gap = np.hypot(x[:, :-1] - x[:, 1:], y[:, :-1] - y[:, 1:])
        self.collided = self.gap < self._half_sum

    def _reward(self, err, accel, jerk, yaw_rate) -> np.ndarray:
        c = self.reward_config
        e = np.abs(err) / c.spacing_scale_m
        e = np.where(np.isnan(e), 0.0, np.minimum(e, 1.0))
        a = accel / c.accel_scale_mps2
        j = jerk / c.jerk_scale_mps3
        w = yaw_rate / c.yaw_rate_scale_radps
        return -(
            c.w_spacing * e
            + c.w_accel * a * a
            + c.w_jerk * j * j
            + c.w_yaw_rate * w * w
            + np.where(self.collided, c.collision_penalty, 0.0)
        )

    def _infos(self) -> dict[str, Any]:
        """Arrays (B, N-1) of ``ConvoyEnv``'s info keys (NaN where it has None), plus
        ``mode`` codes (``MODES``); ``leader_*`` (B,): the leader's values of the keys a
        log row has (``experiments.batched`` writes the leader's rows from them)."""
        nan_cmd = ~self._has_cmd[:, None]
        cmd_v = np.where(nan_cmd, np.nan, self.cmd_v[:, 1:])
        cmd_dh = np.where(nan_cmd, np.nan, self.cmd_dh[:, 1:])
        return {
            "t_s": self.t.copy(),
            "gap_m": self.gap.copy(),
            "desired_gap_m": self.desired_gap[:, 1:].copy(),
            "platooning_error_m": np.abs(self.gap - self.desired_gap[:, 1:]),
            "spacing_error_m": self.spacing_error[:, 1:].copy(),
            "speed_mps": self.own[2][:, 1:].copy(),
            "accel_mps2": self.own[4][:, 1:].copy(),
            "leader_speed_mps": self.own[2][:, 0].copy(),
            "cmd_speed_mps": cmd_v,
            "cmd_heading_change_rad": cmd_dh,
            "mode": self.modes[:, 1:].copy(),
            "collision": self.collided.copy(),
            "msgs_sent": self.msgs_sent[:, 1:].copy(),
            "msgs_received": self.delivered_to[:, 1:].copy(),
            "msgs_kept": self.msgs_kept[:, 1:].copy(),
            "msgs_lost": self.lost_to[:, 1:].copy(),
            "pred_msg_age_s": self.pred_age[:, 1:].copy(),
            "policy_errors": self.policy_errors[:, 1:].copy(),
            "leader_cmd_speed_mps": np.where(nan_cmd[:, 0], np.nan, self.cmd_v[:, 0]),
            "leader_cmd_heading_change_rad": np.where(nan_cmd[:, 0], np.nan, self.cmd_dh[:, 0]),
            "leader_mode": self.modes[:, 0].copy(),
            "leader_msgs_sent": self.msgs_sent[:, 0].copy(),
            "leader_msgs_received": self.delivered_to[:, 0].copy(),
            "leader_msgs_lost": self.lost_to[:, 0].copy(),
        }
>>>>>>> main
