"""VectorConvoyEnv: ``num_envs`` convoys stepped together as struct-of-arrays.

The same tick as ``ConvoyEnv`` (plant, channel, Tx and Rx gates, R^i buffers and trails,
staleness ladder, observation layout v1, braking-aware emergency stop, faults, reward)
over every convoy and vehicle at once, in compiled kernels (numba, the ``batched``
extra; ``vector.jit``): one call per stage, no Python loop over vehicles or convoys in
the step. Convoy ``b`` reset with seed ``s`` reproduces ``ConvoyEnv.reset(seed=s)`` for
the same actions: the same deliveries (counter-based draws, ``comms.loss``), modes and
terminations, and states within float rounding (``tests/envs/test_vector_env.py``).

The parts: ``vector.links`` (which links a topology keeps, index tables),
``vector.plant``, ``vector.leader``, ``vector.channel`` (Tx gates, loss, latency),
``vector.rx`` (R^i buffers) and ``vector.trail``, ``vector.member`` (estimate, ladder,
emergency stop), ``vector.observation``, ``vector.measures`` (gaps, reward, infos),
``vector.events`` (``safety_events(b)``: ``ConvoyEnv``'s list, built when asked).
Per-vehicle work follows the kept links, so a ``lookahead:K`` convoy costs O(N·K): loss
is drawn on the links the members keep (``link_counters="kept"``, the default), or on
every ordered pair (``"all"``: ``ConvoyEnv``'s counters, for logs that must match it).

Arrays: observations ``(B, N-1, D)`` float32 (followers in order), actions
``(B, N-1, 2)``; rewards ``(B, N-1)``; ``terminated``/``truncated`` ``(B,)``. GPS noise
(``vector.gps``): the members see and send ``sensed``, the plant state with noisy
positions. Ranging sensors (``vector.ranging``: the same counter-based noise as
``ConvoyEnv``) feed the ladder and the emergency rule; ``forge`` faults (``vector.forge``)
are rejected and counted (``forged_rejected``) or, with ``auth=False``, delivered into R^i.
Not supported (a ConfigError says so): traffic scenarios, rendering.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np

from openconvoy.comms.loss import LossConfig, as_loss_config
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_fault_times, check_faults, parse_fault
from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import ObservationLayout
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.core.safety import for_vehicle
from openconvoy.envs.convoy_env import check_episode_args, check_rate_and_noise
from openconvoy.envs.gps import gps_key
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.scenarios import PathScenario, make_scenario
from openconvoy.envs.vector.channel import VectorChannel
from openconvoy.envs.vector.events import Event, SafetyEvents
from openconvoy.envs.vector.forge import Forgers
from openconvoy.envs.vector.gps import sense
from openconvoy.envs.vector.leader import LeaderDriver
from openconvoy.envs.vector.links import build_links
from openconvoy.envs.vector.measures import info_arrays, infos, measure, pack_reward, reward
from openconvoy.envs.vector.member import (
    COOP,
    FAILSAFE,
    STOP,
    Commands,
    Member,
    decide,
    lead_guard,
    pack_ladder,
    pack_spacing,
)
from openconvoy.envs.vector.observation import TG_ROWS, Measures, Sources, observe, pack_layout
from openconvoy.envs.vector.plant import ACCEL, VectorPlant
from openconvoy.envs.vector.ranging import RangingSensors
from openconvoy.envs.vector.rx import RxBuffers
from openconvoy.envs.vector.step import FusedCall, pack
from openconvoy.envs.vector.threads import make_slabs, thread_count
from openconvoy.envs.vector.trail import needs_wider, window
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset

MODES = ("coop", "degraded", "stop", "failsafe")
"""Mode names by code in the mode arrays (``MODES[code]`` is the log's name)."""
__all__ = ["COOP", "FAILSAFE", "MODES", "STOP", "VectorConvoyEnv"]


def _per_convoy_loss(
    loss: LossConfig | float | Sequence[LossConfig] | None,
    B: int,
    per: float | Sequence[float] | None = None,
) -> list[LossConfig]:
    """One LossConfig per convoy; a sequence may differ only in ``per`` (a batched sweep).
    ``loss`` a number, or ``per`` (a number, or one per convoy): packet error rates
    (``comms.loss.as_loss_config``)."""
    if per is not None and not isinstance(per, (int, float)):
        pers = [float(p) for p in per]
        if len(pers) != B:
            raise ConfigError(f"per: need one packet error rate per convoy ({B}), got {len(pers)}")
        base = _per_convoy_loss(loss, B)
        return [as_loss_config(c, p) for c, p in zip(base, pers)]
    if loss is None or isinstance(loss, (LossConfig, int, float)):
        return [as_loss_config(loss, per)] * B
    out = [as_loss_config(c, per) for c in loss]
    if len(out) != B:
        raise ConfigError(f"loss: need one LossConfig per convoy ({B}), got {len(out)}")
    same = lambda c: (c.model, c.mean_burst_s, c.latency, c.link_latency_s)  # noqa: E731
    if any(same(c) != same(out[0]) for c in out[1:]):
        raise ConfigError("loss: the convoys' LossConfigs may differ only in per")
    return out


MAX_NUM_ENVS = 1_000_000
"""Most convoys one ``VectorConvoyEnv`` holds (its arrays grow with it: 10**7 ran out of
memory, issue 22 D68)."""


def _check_args(
    num_envs: int, control_rate_hz: float, gps_noise_m: float, render_mode: str | None
) -> None:
    if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
        raise ConfigError(f"num_envs: expected an integer, got {num_envs!r}")
    if not 1 <= int(num_envs) <= MAX_NUM_ENVS:
        raise ConfigError(f"num_envs must be in 1..{MAX_NUM_ENVS}, got {num_envs}")
    check_rate_and_noise(control_rate_hz, gps_noise_m)
    if render_mode is not None:
        raise ConfigError("VectorConvoyEnv does not render (use ConvoyEnv)")


def _check_counters(link_counters: str) -> None:
    """``link_counters`` is ``kept`` or ``all``."""
    if link_counters not in ("all", "kept"):
        raise ConfigError(f"link_counters must be 'kept' or 'all', got {link_counters!r}")


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
    return built


class VectorConvoyEnv:
    """``num_envs`` convoys of a scenario-driven leader and ``n`` followers, batched.

    Arguments after ``num_envs`` are ``ConvoyEnv``'s (see there); ``reset(seed=s)`` seeds
    convoy ``b`` with ``s + b`` (or ``seed`` may be a sequence of B seeds).
    ``autoreset``: a convoy whose episode ended is reset within the same ``step``
    (its seed sequence continued, as ``ConvoyEnv.reset()`` without a seed) and the
    observation returned is the new episode's first; the final one is in
    ``infos["final_observation"]``, and ``infos["final_safety_events"][b]`` is each ended
    convoy's ``safety_events(b)``.
    ``link_counters``: ``"kept"`` (default) draws loss only on the links a member keeps
    (ρ's, its predecessor's and, for the leader, everyone's: the only draws that change
    a delivery into R^i), O(N·K) per step for ``lookahead:K``; ``msgs_received`` and
    ``msgs_lost`` then count those links. ``"all"`` draws on every ordered pair, as
    ``ConvoyEnv``, so the counters match its (the same deliveries into R^i either way,
    hence the same run). ``msgs_offered``, what the other vehicles broadcast, is the
    same in both (closed form; ``msgs_received + msgs_lost`` under ``"all"`` with
    instant links).
    ``threads``: how many threads a step may use (default: the cores this process may
    run on, capped by ``NUMBA_NUM_THREADS``); the batch is cut into slabs of at least
    ``vector.threads.MIN_SLAB`` convoys, with the same results whatever the count.
    """

    def __init__(
        self,
        num_envs: int,
        scenario: str | PathScenario = "paper",
        n_followers: int | None = None,
        member_config: MemberConfig | None = None,
        loss: LossConfig | float | Sequence[LossConfig] | None = None,
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
        link_counters: str = "kept",
        per: float | Sequence[float] | None = None,
        threads: int | None = None,
    ) -> None:
        _check_args(num_envs, control_rate_hz, gps_noise_m, render_mode)
        check_episode_args(n_followers, max_time_s)
        self.scenario = sc = _scenario(scenario, n_followers, vehicle_presets)
        self.num_envs = B = int(num_envs)
        self.n_vehicles = N = sc.n_vehicles
        self.losses = _per_convoy_loss(loss, B, per)
        self.loss = max(self.losses, key=lambda c: c.per)
        _check_counters(link_counters)
        self.faults = tuple(f if isinstance(f, Fault) else parse_fault(f) for f in faults)
        check_faults(self.faults, N)
        self.presets = tuple(sc.presets)
        if any(p.heading_bias_rad for p in self.presets):
            raise ConfigError(
                "a heading bias (heading_bias_rad) is the scalar simulator's (ConvoyEnv), "
                "not the batched one's"
            )
        self.autoreset, self.link_counters, self.render_mode = autoreset, link_counters, None
        self.control_rate_hz = float(control_rate_hz)
        self.gps_noise_m = float(gps_noise_m)
        self.dt = 1.0 / self.control_rate_hz
        self.max_time_s = float(sc.duration_s if max_time_s is None else max_time_s)
        self.max_steps = max(1, int(round(self.max_time_s / self.dt)))
        check_fault_times(self.faults, self.max_time_s)
        self.reward_config = reward_config or RewardConfig()
        self.member_config = mc = member_config or MemberConfig(spacing=sc.spacing)
        compiled_only = [p for p in mc.plugins if not p.startswith("topology ")]
        if compiled_only:  # a plug-in σ or τ is Python: the kernels cannot call it
            raise ConfigError(
                f"VectorConvoyEnv compiles the built-in spacing and trigger only, not the plug-in "
                f"{', '.join(compiled_only)} (use ConvoyEnv)"
            )
        self.layout: ObservationLayout = mc.layout
        self.emergency_stop = bool(emergency_stop)
        self.possible_agents = [f"follower_{i}" for i in range(1, N)]
        self._constants(gap_margin_m)
        self.links = build_links(mc, N)
        self.L = self.links.L
        self.plant = VectorPlant(self.presets, self.dt, B)
        self.leader = LeaderDriver(sc, B)
        self.channel = VectorChannel(
            B, self.links, self.losses, mc.trigger, self.faults, self.dt, link_counters == "all"
        )
        self.rx = RxBuffers(B, self.links, mc.k, mc.trail_spacing_m, self._trail_window())
        self.ranging = RangingSensors(self.presets, B)
        self.forgers = Forgers(self.faults, B, N, self.dt, bool(auth))
        self._seed_seqs: list[np.random.SeedSequence | None] = [None] * B
        self.t: np.ndarray = np.zeros(B)
        self.step_count = np.zeros(B, dtype=np.int64)
        self._alloc()
        self._fused = pack(self) if self._fusable() else None
        self.threads = thread_count(threads)
        self._slabs = (
            make_slabs(self, self._fused, self.threads, FusedCall)
            if self._fused is not None
            else None
        )

    def _trail_window(self) -> int:
        """Breadcrumbs a trail's ring holds at first (``vector.trail.window``): the fewest
        that hold a tick's progress at the fastest preset's top speed. The reads widen it
        to the horizon they reach (``_widen_trails``): a ring sized up front to the
        farthest target's gap at top speed (256 for ``paper``) was most of a convoy's
        memory at large batches, read only in its newest part at lower speeds."""
        P = self.presets
        vmax = max(p.max_speed_mps for p in P)
        return window(0.0, self.member_config.trail_spacing_m, vmax * self.dt)

    def _widen_trails(self) -> None:
        """Double the trails' rings while a read went back into their last quarter
        (``vector.trail.needs_wider``): before a tick could read past them. The stages
        are packed again around the new arrays."""
        if not needs_wider(self.rx.reach(), self.rx.window):
            return
        w = self.rx.window
        while needs_wider(self.rx.reach(), w):
            w *= 2
        if self._slabs is not None:  # its views of the rings go with the old buffer
            self._slabs.close()
        self.rx.widen(w)
        self._sources = self._observed()  # around the new rings
        if self._fused is not None:
            self._fused = pack(self)
            if self._slabs is not None:
                self._slabs = make_slabs(self, self._fused, self.threads, FusedCall)

    def _observed(self) -> Sources:
        """What ``observe`` reads (``vector.observation.Sources``) of the arrays now held:
        built again when the trails' rings widen."""
        lk, rx = self.links, self.rx
        return Sources(
            hist=rx.hist,
            hist_n=rx.hist_n,
            newest=rx.newest,
            trail=rx.trail,
            tail=rx.tail,
            trail_n=rx.trail_n,
            hint=rx.hint,
            hint_k=rx.hint_k,
            trail_of=lk.trail_of,
            slot_link=lk.slot_link,
            target_link=lk.target_link,
            pred_link=lk.pred_link,
            link_decel=self._link_decel,
            lengths=self.lengths,
            spacing=self._spacing,
            stop_after=float(self.member_config.ladder.stop_after_s),
            fresh_age=float(self._fresh_age_s),
            geom=self._geom,
        )

    def _fusable(self) -> bool:
        """Every stage has a kernel: one compiled call per tick (``vector.step``)."""
        instant_bernoulli = self.channel.ge is None and self.channel.slots == 0
        staged_only = self.ranging.any or self.forgers.delivers or bool(self._brakes)
        return (
            instant_bernoulli
            and self.leader.kind != 0
            and self.gps_noise_m == 0.0
            and not staged_only
        )

    def _constants(self, gap_margin_m: float | None) -> None:
        """The kernels' per-vehicle constants and packed configs."""
        P, mc = self.presets, self.member_config
        self.lengths = np.array([p.length_m for p in P])
        self._half_sum = 0.5 * (self.lengths[1:] + self.lengths[:-1])
        decel = np.array([p.decel_max_mps2 for p in P], dtype=float)
        self._decel = np.where(decel > 0.0, decel, np.inf)
        self._rules = rules = [
            for_vehicle(p.decel_max_mps2, p.actuation_delay_s, p.speed_lag_s, p.length_m, gap_margin_m,
                        self.dt)
            for p in P
        ]  # fmt: skip
        packed = np.array([[r.decel_mps2, r.reaction_s, r.margin_m, r.lag_s] for r in rules]).T
        self._rule = packed[:, 1:].copy()  # the followers'
        self._lead_rule = packed[:, 0].copy()
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
        self.modes = np.zeros((B, N), dtype=np.int8)  # codes of MODES
        self.cmd_v = np.zeros((B, N))
        self.cmd_dh = np.zeros((B, N))
        self.estopped = np.zeros((B, N), dtype=bool)
        self.policy_failed = np.zeros((B, N), dtype=bool)
        self.policy_errors = np.zeros((B, N), dtype=np.int64)
        self.events = SafetyEvents(self.faults, self._rules, B, N, self.dt)
        self.desired_gap = np.full((B, N), np.nan)
        self.spacing_error = np.full((B, N), np.nan)
        self.pred_age = np.full((B, N), np.nan)
        self.pred_est = np.full((2, B, N), np.nan)  # arc to head, closing
        self._has_cmd = np.zeros(B, dtype=bool)
        # A view, for the kernels: with the heading's cosine and sine (vector_plant).
        self._own = self.plant.state.reshape(-1, B, N)
        # What the members measure of themselves: the plant state, or a noisy copy.
        self._sensed = self._own if self.gps_noise_m == 0.0 else np.zeros((6, B, N))
        self._gps_keys = np.zeros(B, dtype=np.uint64)
        self._cmd_v_flat, self._cmd_dh_flat = self.cmd_v.reshape(-1), self.cmd_dh.reshape(-1)
        self._everyone = np.ones(B, dtype=bool)
        self._fused_call = FusedCall()
        self._fresh_age_s = self.member_config.fresh_age_s
        self._rule_fresh_s = self.member_config.rule_fresh_age_s  # decide's and lead_guard's
        self._targets_scratch = np.zeros((TG_ROWS, len(self.layout.targets)))
        self._accel_old = np.zeros((B, N))
        self.max_heading_change = MAX_HEADING_CHANGE_RAD
        self.gap = np.zeros((B, N - 1))
        self.collided = np.zeros((B, N - 1), dtype=bool)
        lk, rx = self.links, self.rx
        self._member = Member(
            low=self.action_low,
            high=self.action_high,
            hist=rx.hist,
            hist_n=rx.hist_n,
            newest=rx.newest,
            needed=lk.needed,
            pred_link=lk.pred_link,
            lead_link=lk.lead_link,
            link_decel=self._link_decel,
            decel=self._decel,
            lengths=self.lengths,
            spacing=self._spacing,
            ladder=self._ladder,
            fresh_age=float(self._rule_fresh_s),
            max_dh=MAX_HEADING_CHANGE_RAD,
            rule=self._rule,
            lead_rule=self._lead_rule,
            emergency=self.emergency_stop,
        )
        self._sources = self._observed()
        self._measures = Measures(
            self.desired_gap,
            self.spacing_error,
            self.pred_age,
            self.pred_est,
            self._targets_scratch,
        )
        self._commands = Commands(
            errors=self.policy_errors,
            failed=self.policy_failed,
            estopped=self.estopped,
            cmd_v=self.cmd_v,
            cmd_dh=self.cmd_dh,
            modes=self.modes,
            events=self.events.record,
            n_events=self.events.count,
        )

    # --- API ------------------------------------------------------------------------

    @property
    def single_observation_space(self) -> gymnasium.spaces.Box:
        """One follower's observation: ``ConvoyEnv``'s, the layout's bounds, float32."""
        low, high = self.layout.bounds()
        return gymnasium.spaces.Box(low, high, dtype=np.float32)

    @property
    def single_action_space(self) -> gymnasium.spaces.Box:
        """One follower's action ``[speed m/s, heading change rad]``: the widest followers'
        bounds (each vehicle clips to its own, ``action_low``/``action_high``)."""
        return gymnasium.spaces.Box(
            low=self.action_low.min(axis=0).astype(np.float32),
            high=self.action_high.max(axis=0).astype(np.float32),
            dtype=np.float32,
        )

    @property
    def observation_space(self) -> gymnasium.spaces.Box:
        """What ``reset`` and ``step`` return: ``(num_envs, N-1, D)``, float32."""
        low, high = self.layout.bounds()
        shape = (self.num_envs, self.n_vehicles - 1, self.layout.size)
        low, high = np.broadcast_to(low, shape), np.broadcast_to(high, shape)
        return gymnasium.spaces.Box(low.copy(), high.copy(), dtype=np.float32)

    @property
    def action_space(self) -> gymnasium.spaces.Box:
        """What ``step`` takes: ``(num_envs, N-1, 2)``, each follower its own bounds."""
        low = np.broadcast_to(self.action_low, (self.num_envs, *self.action_low.shape))
        high = np.broadcast_to(self.action_high, (self.num_envs, *self.action_high.shape))
        return gymnasium.spaces.Box(
            low=low.astype(np.float32), high=high.astype(np.float32), dtype=np.float32
        )

    @property
    def own(self) -> np.ndarray:
        """The plant state (6, B, N): x, y, speed, heading, accel, yaw rate (a view)."""
        return self._own[:6]

    @property
    def forged_rejected(self) -> np.ndarray:
        """Forged messages each member rejected so far (B, N) (``ConvoyEnv.forged_rejected``)."""
        return self.forgers.rejected(self.step_count)

    @property
    def own_truth(self) -> tuple[np.ndarray, ...]:
        """x, y, speed, heading, accel, yaw rate, each (B, N), a snapshot."""
        return tuple(self.own.copy())

    def safety_events(self, b: int) -> list[Event]:
        """Convoy ``b``'s ``ConvoyEnv.safety_events`` (t s, vehicle, reason) this episode,
        built when asked (``vector.events``); see ``autoreset`` for a finished one's.
        ``ValueError`` for a ``b`` that is no convoy."""
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)):
            raise ValueError(f"safety_events: convoy index must be an integer, got {b!r}")
        if not 0 <= b < self.num_envs:
            raise ValueError(f"safety_events: convoy {b} out of 0..{self.num_envs - 1}")
        return self.events.of(int(b), int(self.step_count[b]))

    def close(self) -> None:
        """Stop the step's threads, if any (the Gymnasium vector API's ``close``)."""
        if self._slabs is not None:
            self._slabs.close()

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
        self._widen_trails()
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
            ss_channel, ss_gps, ss_ranging, _ = seq.spawn(4)  # ConvoyWorld.reset's spawn
            self.channel.seed(b, np.random.default_rng(ss_channel))
            self._gps_keys[b] = np.uint64(gps_key(np.random.default_rng(ss_gps)))
            self.ranging.seed(b, ss_ranging)
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
        self.events.reset(which)

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One tick of every convoy with ``actions`` ``(B, N-1, 2)`` (SI, clipped)."""
        B, N = self.num_envs, self.n_vehicles
        a = np.ascontiguousarray(actions, dtype=np.float32)  # one compiled layout
        if a.shape != (B, N - 1, 2):
            raise ValueError(f"actions must have shape {(B, N - 1, 2)}, got {a.shape}")
        obs = np.empty((B, N - 1, self.layout.size), dtype=np.float32)
        rewards = np.empty((B, N - 1))
        if self._fused is not None:
            terminated, truncated = np.empty(B, dtype=bool), np.empty(B, dtype=bool)
            filled = info_arrays(B, N - 1)
            if self._slabs is not None:
                self._slabs.step(a, obs, rewards, terminated, truncated, filled)
            else:
                self._fused_call(a, obs, rewards, terminated, truncated, filled, self._fused)
            info = infos(self, filled)
        else:
            terminated, truncated, info = self._staged_step(a, obs, rewards)
        done = terminated | truncated
        if self.autoreset and done.any():
            info["final_observation"] = obs.copy()
            info["final_safety_events"] = self.events.finished(done, self.step_count)
            self._reset_convoys(done, [None] * B)
            self._tick(done, obs)
            measure(self.own, self._half_sum, self.gap, self.collided)
        self._widen_trails()
        return obs, rewards, terminated, truncated, info

    def step_fused(
        self,
        a: np.ndarray,
        obs: np.ndarray,
        rewards: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        filled: tuple[np.ndarray, ...],
    ) -> bool:
        """``step``'s tick into the caller's arrays (actions ``a`` float32 ``(B, N-1, 2)``,
        C-contiguous, within float32; ``filled``: ``measures.info_arrays``), without the
        info dict or autoreset: ``ConvoyEnv``'s compiled tick (``envs.compiled``). False,
        with nothing done, where this env steps stage by stage or on threads."""
        if self._fused is None or self._slabs is not None:
            return False
        self._fused_call(a, obs, rewards, terminated, truncated, filled, self._fused)
        self._widen_trails()
        return True

    def _staged_step(
        self, a: np.ndarray, obs: np.ndarray, rewards: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """``fused_step``'s stages one call each (what a kernel cannot do is here)."""
        accel_old = self._command(a)
        self.step_count += 1
        np.multiply(self.step_count, self.dt, out=self.t)
        self._tick(self._everyone, obs)
        own = self.own
        measure(own, self._half_sum, self.gap, self.collided)
        reward(rewards, self.gap, self.desired_gap, accel_old, own, self.collided,
               1.0 / self.dt, self._reward_c)  # fmt: skip
        terminated = np.asarray(self.collided.any(axis=1))
        truncated = (self.step_count >= self.max_steps) & ~terminated
        return terminated, truncated, infos(self)

    def _command(self, a: np.ndarray) -> np.ndarray:
        """The members decide, the leaders drive, faults act, the plant moves ``dt``;
        returns the accelerations before the move (B, N)."""
        t, own = self.t, self.own
        self.ranging.read(own, self.step_count)  # the true state, before the plant moves
        # on what the members measured of themselves at the last tick
        sensed, reading = self._sensed, self.ranging.reading
        decide(a, t, sensed, reading, self.pred_est, self._member, self._commands)
        self.leader.command(t, own, self.cmd_v, self.cmd_dh)
        lead_guard(t, sensed, self._member, self._commands)
        for vehicle, t_from in self._brakes:
            on = t >= t_from
            self.cmd_v[on, vehicle] = 0.0
            self.cmd_dh[on, vehicle] = 0.0
            self.modes[on, vehicle] = STOP
        self._has_cmd[:] = True
        accel_old = self._accel_old
        accel_old[:] = own[ACCEL]
        self.plant.step(self._cmd_v_flat, self._cmd_dh_flat)
        return accel_old

    def _tick(self, which: np.ndarray, obs: np.ndarray) -> None:
        """Own states -> Tx -> channel -> Rx -> observations ``obs`` at ``self.t``, for
        the convoys ``which``."""
        own, lk, rx = self._sensed, self.links, self.rx
        if own is not self._own:
            sense(self._own, self.step_count, self._gps_keys, self.gps_noise_m, which, own)
        self.channel.transmit(self.t, self.step_count, own, which, rx)
        self.forgers.deliver(self.t, which, self._own, lk, self.channel.msgs_kept, rx)
        observe(obs, which, self.t, own, self._sources, self._measures)
