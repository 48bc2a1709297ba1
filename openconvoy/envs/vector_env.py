"""VectorConvoyEnv: ``num_envs`` convoys stepped together as struct-of-arrays numpy.

The same tick as ``ConvoyEnv`` (plant, channel, Tx and Rx gates, R^i buffers and trails,
staleness ladder, observation layout v1, braking-aware emergency stop, faults, reward),
written with array operations over every convoy and vehicle at once: the step has no
Python loop over vehicles or convoys (only over the few observation slots, trail-walk
iterations and latency slots). Convoy ``b`` reset with seed ``s`` reproduces
``ConvoyEnv.reset(seed=s)`` for the same actions: the same deliveries (the channel's
Bernoulli draws are counter-based, ``comms.loss.counter_uniform``), modes and
terminations, and states within float rounding (``tests/envs/test_vector_env.py``).

Per-vehicle work follows the links the topology keeps (receiver, sender): the R^i
buffers (``k`` states, newest first) and trails (breadcrumb rings) exist only for those,
so a ``lookahead:K`` convoy costs O(N·K); the loss draws and message counters cover
every ordered pair (the counters ``ConvoyEnv`` reports count every receiver).

Arrays: observations ``(B, N-1, D)`` float32 (followers in order), actions
``(B, N-1, 2)``; rewards ``(B, N-1)``; ``terminated``/``truncated`` ``(B,)``. Not yet
supported (a ConfigError says so): GPS noise, ranging sensors, ``forge`` faults,
latency jitter, traffic scenarios.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from openconvoy.comms.loss import (
    GE_ADVANCE,
    GE_INIT,
    GE_LOSS,
    GilbertElliott,
    LossConfig,
    counter_uniform_array,
)
from openconvoy.core.errors import ConfigError
from openconvoy.core.faults import Fault, check_faults, parse_fault
from openconvoy.core.gates import RxGate
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.member import MemberConfig
from openconvoy.core.observation import LOOKAHEAD_S, MAX_AGE_S, ObservationLayout
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.core.safety import for_vehicle
from openconvoy.envs.channel import DRAW_LOSS
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.scenarios import (
    EMERGENCY_BRAKE_AT_S,
    EMERGENCY_DECEL_MPS2,
    EMERGENCY_SPEED_MPS,
    PathScenario,
    emergency_speed,
    make_scenario,
    paper_speed,
)
from openconvoy.envs.vehicles import VehiclePreset, vehicle_preset

TWO_PI = 2.0 * math.pi
MODES = ("coop", "degraded", "stop", "failsafe")
COOP, DEGRADED, STOP, FAILSAFE = range(4)
"""Mode codes in the mode arrays (``MODES[code]`` is the log's name)."""
TRAIL_CAPACITY = 1024
"""Breadcrumbs per trail, as ``core.trail.Trail`` (the oldest half dropped when full)."""
_BISECT_STEPS = int(math.ceil(math.log2(TRAIL_CAPACITY + 1))) + 1


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.remainder(a + math.pi, TWO_PI) - math.pi


def _paper_speed(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    return np.where((t >= 20.0) & (t < 40.0), 2.0, 1.0)


def _emergency_speed(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    braking = np.maximum(
        0.0, EMERGENCY_SPEED_MPS - EMERGENCY_DECEL_MPS2 * (t - EMERGENCY_BRAKE_AT_S)
    )
    return np.where(t < EMERGENCY_BRAKE_AT_S, EMERGENCY_SPEED_MPS, braking)


_ARRAY_PROFILES = {paper_speed: _paper_speed, emergency_speed: _emergency_speed}


class _LeaderDriver:
    """``PathScenario.leader_command`` for B leaders at once (same arithmetic)."""

    def __init__(self, scenario: PathScenario, num_envs: int) -> None:
        self.sc = scenario
        path = scenario.path
        self.path = path
        prof = scenario.speed_profile
        self.profile = _ARRAY_PROFILES.get(prof)
        if self.profile is None:
            probe = prof(0.0, 0.0)
            if not isinstance(probe, (int, float)):
                raise ConfigError(
                    "VectorConvoyEnv: the scenario's speed profile must return a number"
                )
            self.profile = lambda t, s: np.vectorize(prof, otypes=[float])(t, s)  # noqa: E731
        self.B = num_envs
        self._a = path._a
        self._dir = path._seg_dir
        self._len = path._seg_len
        self._s0 = path._s
        self.reset(np.ones(num_envs, dtype=bool))

    def reset(self, which: np.ndarray) -> None:
        sc = self.sc
        s0 = sc.leader_start_s % self.path.length if self.path.closed else sc.leader_start_s
        if not hasattr(self, "s"):
            self.s = np.zeros(self.B)
            self.cmd = np.zeros(self.B)
            self.t_last = np.full(self.B, np.nan)
        self.s[which] = s0
        self.cmd[which] = float(sc.start_speed_mps)
        self.t_last[which] = np.nan

    def _segment(self, s: np.ndarray) -> np.ndarray:
        i = np.searchsorted(self._s0, s, side="right") - 1
        return np.clip(i, 0, len(self._len) - 1)

    def _project(self, x: np.ndarray, y: np.ndarray, hint: np.ndarray) -> np.ndarray:
        path = self.path
        n = len(self._len)
        if n == 1:
            ax, ay = path._a_list[0]
            dx, dy = path._dir_list[0]
            return np.minimum(np.maximum((x - ax) * dx + (y - ay) * dy, 0.0), path.length)
        window = 20.0
        if n <= 2:
            idx = np.broadcast_to(np.arange(n), (len(x), n))
            ok = np.ones_like(idx, dtype=bool)
        elif path.closed:
            i0 = self._segment(np.remainder(hint - window, path.length))
            i1 = self._segment(np.remainder(hint + window, path.length))
            span = np.minimum((i1 - i0) % n + 1, n)
            width = int(span.max())
            off = np.arange(width)
            idx = (i0[:, None] + off) % n
            ok = off < span[:, None]
        else:
            i0 = self._segment(np.maximum(hint - window, 0.0))
            i1 = self._segment(np.minimum(hint + window, path.length))
            span = i1 - i0 + 1
            width = int(span.max())
            off = np.arange(width)
            idx = np.minimum(i0[:, None] + off, n - 1)
            ok = off < span[:, None]
        a = self._a[idx]
        d = self._dir[idx]
        u = np.clip(
            (x[:, None] - a[..., 0]) * d[..., 0] + (y[:, None] - a[..., 1]) * d[..., 1],
            0.0,
            self._len[idx],
        )
        px = a[..., 0] + d[..., 0] * u
        py = a[..., 1] + d[..., 1] * u
        dist = np.where(ok, (px - x[:, None]) ** 2 + (py - y[:, None]) ** 2, np.inf)
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(x))
        s = self._s0[idx[rows, k]] + u[rows, k]
        return np.remainder(s, path.length) if path.closed else s

    def _point_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.path.closed:
            s = np.remainder(s, self.path.length)
        i = self._segment(s)
        u = s - self._s0[i]
        return self._a[i, 0] + self._dir[i, 0] * u, self._a[i, 1] + self._dir[i, 1] * u

    def command(self, t, x, y, heading, speed) -> tuple[np.ndarray, np.ndarray]:
        sc, path = self.sc, self.path
        self.s = self._project(x, y, self.s)
        target = np.asarray(self.profile(t, self.s), dtype=float) * np.ones_like(t)
        if not path.closed:
            remaining = np.maximum(path.length - self.s, 0.0)
            target = np.minimum(target, np.sqrt(2.0 * sc.ramp_decel_mps2 * remaining))
        dt = np.where(np.isnan(self.t_last), 0.0, np.maximum(t - self.t_last, 0.0))
        self.t_last = t.copy()
        dv = target - self.cmd
        step = np.minimum(np.maximum(dv, -sc.ramp_decel_mps2 * dt), sc.ramp_accel_mps2 * dt)
        self.cmd = np.where(dt > 0.0, self.cmd + step, self.cmd)
        look = np.maximum(sc.lookahead_min_m, sc.lookahead_time_s * np.maximum(speed, 0.0))
        ahead = np.remainder(self.s + look, path.length) if path.closed else self.s + look
        tx, ty = self._point_at(ahead)
        return self.cmd.copy(), np.arctan2(ty - y, tx - x)


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
        if num_envs < 1:
            raise ConfigError(f"num_envs must be at least 1, got {num_envs}")
        if control_rate_hz <= 0:
            raise ConfigError(f"control_rate_hz must be positive, got {control_rate_hz}")
        if gps_noise_m != 0.0:
            raise ConfigError("VectorConvoyEnv does not support gps_noise_m yet (use ConvoyEnv)")
        if render_mode is not None:
            raise ConfigError("VectorConvoyEnv does not render (use ConvoyEnv)")
        presets = None
        if vehicle_presets is not None:
            presets = [
                p if isinstance(p, VehiclePreset) else vehicle_preset(p) for p in vehicle_presets
            ]
        if isinstance(scenario, str):
            scenario = make_scenario(scenario, n_followers, presets)
        if not isinstance(scenario, PathScenario):
            raise ConfigError(
                "VectorConvoyEnv supports path scenarios (paper, track, emergency-braking, track-file)"
            )
        if scenario.n_vehicles < 2:
            raise ConfigError("a convoy needs a leader and at least one follower")
        self.losses = self._per_convoy_loss(loss, int(num_envs))
        self.loss = max(self.losses, key=lambda c: c.per)
        self._per = np.array([c.per for c in self.losses])
        probe = self.loss.make()
        self._ge = probe if isinstance(probe, GilbertElliott) else None
        if self._ge is not None:
            # Per convoy: the chain for its PER (a PER of 0 is a perfect link, as ConvoyEnv's).
            self._ge_good = np.array(
                [
                    c.mean_burst_s * (1.0 - c.per) / c.per if c.per > 0 else np.inf
                    for c in self.losses
                ]
            )
        if self.loss.jitter_s > 0.0:
            raise ConfigError("VectorConvoyEnv does not support latency jitter yet (use ConvoyEnv)")
        self.scenario = scenario
        self.presets = tuple(scenario.presets)
        if any(p.ranging for p in self.presets[1:]):
            raise ConfigError("VectorConvoyEnv does not model ranging sensors yet (use ConvoyEnv)")
        self.faults = tuple(f if isinstance(f, Fault) else parse_fault(f) for f in faults)
        if any(f.forges for f in self.faults):
            raise ConfigError("VectorConvoyEnv does not model forge faults (use ConvoyEnv)")
        self.num_envs = B = int(num_envs)
        self.n_vehicles = N = scenario.n_vehicles
        check_faults(self.faults, N)
        self.autoreset = autoreset
        self.render_mode = None
        if link_counters not in ("all", "kept"):
            raise ConfigError(f"link_counters must be 'all' or 'kept', got {link_counters!r}")
        self.link_counters = link_counters
        if link_counters == "kept" and (
            self.loss.latency_s > 0.0 or (self.loss.per > 0.0 and self.loss.model != "bernoulli")
        ):
            raise ConfigError("link_counters='kept' supports instant Bernoulli links only")
        self.control_rate_hz = float(control_rate_hz)
        self.dt = 1.0 / self.control_rate_hz
        self.max_time_s = float(scenario.duration_s if max_time_s is None else max_time_s)
        self.max_steps = max(1, int(round(self.max_time_s / self.dt)))
        self.reward_config = reward_config or RewardConfig()
        self.member_config = mc = member_config or MemberConfig(spacing=scenario.spacing)
        self.layout: ObservationLayout = mc.layout
        self.emergency_stop = bool(emergency_stop)
        self.possible_agents = [f"follower_{i}" for i in range(1, N)]

        self.lengths = np.array([p.length_m for p in self.presets])
        self._half_sum = 0.5 * (self.lengths[1:] + self.lengths[:-1])
        decel = np.array([p.decel_max_mps2 for p in self.presets], dtype=float)
        self._decel = np.where(decel > 0.0, decel, np.inf)
        rules = [
            for_vehicle(
                p.decel_max_mps2, p.actuation_delay_s, p.speed_lag_s, p.length_m, gap_margin_m
            )
            for p in self.presets[1:]
        ]
        self._rule_decel = np.array([r.decel_mps2 for r in rules])
        self._rule_reaction = np.array([r.reaction_s for r in rules])
        self._rule_margin = np.array([r.margin_m for r in rules])
        f32 = np.float32
        self.action_low = np.array([[0.0, float(f32(-MAX_HEADING_CHANGE_RAD))]] * (N - 1))
        self.action_high = np.array(
            [
                [float(f32(p.max_speed_mps)), float(f32(MAX_HEADING_CHANGE_RAD))]
                for p in self.presets[1:]
            ]
        )

        self._build_links()
        self.plant = BicyclePlant(list(self.presets) * B, self.dt, vectorized=True)
        self.leader = _LeaderDriver(scenario, B)
        lat = self.loss.latency_s
        self._instant = lat <= 0.0
        self._slots = 1 if self._instant else int(math.ceil(lat / self.dt)) + 3
        self._seed_seqs: list[np.random.SeedSequence | None] = [None] * B
        self.t = np.zeros(B)
        self.step_count = np.zeros(B, dtype=np.int64)
        self._alloc()

    @staticmethod
    def _per_convoy_loss(
        loss: LossConfig | Sequence[LossConfig] | None, B: int
    ) -> list[LossConfig]:
        """One LossConfig per convoy; a sequence may differ only in ``per`` (a batched sweep)."""
        if loss is None or isinstance(loss, LossConfig):
            return [loss or LossConfig()] * B
        out = list(loss)
        if len(out) != B:
            raise ConfigError(f"loss: need one LossConfig per convoy ({B}), got {len(out)}")
        first = out[0]
        for c in out[1:]:
            if (c.model, c.mean_burst_s, c.latency_s, c.jitter_s) != (
                first.model,
                first.mean_burst_s,
                first.latency_s,
                first.jitter_s,
            ):
                raise ConfigError("loss: the convoys' LossConfigs may differ only in per")
        return out

    # --- static structure ----------------------------------------------------------

    def _build_links(self) -> None:
        """Kept links (receiver >= 1, sender), the slot/target/needed index tables."""
        N, mc, lay = self.n_vehicles, self.member_config, self.layout
        links: list[tuple[int, int]] = []
        index: dict[tuple[int, int], int] = {}
        needed: list[list[int]] = [[] for _ in range(N)]
        for r in range(1, N):
            gate = RxGate(mc.topology, r, N)
            for s in range(N):
                if s != r and gate.keeps(s):
                    index[(r, s)] = len(links)
                    links.append((r, s))
            needed[r] = [index[(r, j)] for j in gate.needed()]
        self.L = L = len(links)
        self._link_r = np.array([r for r, _ in links], dtype=np.int64)
        self._link_s = np.array([s for _, s in links], dtype=np.int64)
        self._link_index = index
        # needed: (N, width) link indices padded with L (a sentinel column of age 0).
        width = max(1, max(len(v) for v in needed))
        self._needed = np.full((N, width), L, dtype=np.int64)
        for r, v in enumerate(needed):
            self._needed[r, : len(v)] = v
        self._needed_any = np.array([bool(v) for v in needed])
        # Observation slots for followers 1..N-1: link index or -1.
        F = N - 1
        nslots = len(lay.slots)
        self._slot_link = np.full((F, nslots), -1, dtype=np.int64)
        for i in range(1, N):
            ids = [
                0,
                *[i - m if i - m >= 0 else None for m in range(1, lay.M + 1)],
                i + 1 if i + 1 < N else None,
            ]
            for k, vid in enumerate(ids):
                if vid is not None and (i, vid) in index:
                    self._slot_link[i - 1, k] = index[(i, vid)]
        # Targets (leader, pred_1..pred_M): link or -1; the leader only when not a pred slot.
        ntg = len(lay.targets)
        self._target_link = np.full((F, ntg), -1, dtype=np.int64)
        self._target_vid = np.zeros((F, ntg), dtype=np.int64)
        for i in range(1, N):
            for k in range(ntg):
                vid = 0 if k == 0 else i - k
                if vid < 0 or (k == 0 and i <= lay.M):
                    continue
                self._target_vid[i - 1, k] = vid
                if (i, vid) in index:
                    self._target_link[i - 1, k] = index[(i, vid)]
        pairs = np.argwhere(self._slot_link >= 0)
        self._slot_pairs = (pairs[:, 0], pairs[:, 1], self._slot_link[pairs[:, 0], pairs[:, 1]])
        # Where each (pair, k, feature) lands in a (B, F*D) view of the observations.
        nf = 7
        within = np.arange(mc.k * nf).reshape(mc.k, nf)
        self._slot_cols = (
            pairs[:, 0, None, None] * lay.size
            + pairs[:, 1, None, None] * lay.slot_size
            + within[None]
        ).ravel()
        self._leader_rows = np.flatnonzero(self._target_link[:, 0] >= 0)
        self._pred_link = np.array([index.get((i, i - 1), -1) for i in range(1, N)], dtype=np.int64)

    def _alloc(self) -> None:
        B, N, L, k = self.num_envs, self.n_vehicles, self.L, self.member_config.k
        self.own = np.zeros((6, B, N))  # x, y, speed, heading, accel, yaw_rate
        self.next_check = np.full((B, N), -np.inf)
        self.last_sent = np.full((5, B, N), np.nan)  # t, x, y, speed, heading
        self.msgs_sent = np.zeros((B, N), dtype=np.int64)
        self.broadcasts = np.zeros((B, N), dtype=np.int64)
        self.delivered_to = np.zeros((B, N), dtype=np.int64)
        self.lost_to = np.zeros((B, N), dtype=np.int64)
        self.msgs_kept = np.zeros((B, N), dtype=np.int64)
        self.keys = np.zeros(B, dtype=np.uint64)
        if self._ge is not None:  # per ordered link: key, state, packets offered, last time
            self.ge_key = np.zeros((B, N, N), dtype=np.uint64)
            self.ge_bad = np.zeros((B, N, N), dtype=bool)
            self.ge_n = np.zeros((B, N, N), dtype=np.int64)
            self.ge_t = np.full((B, N, N), np.nan)
        # R^i: per kept link the last k states, newest first: t, x, y, speed, heading, accel.
        self.hist = np.zeros((6, B, L, k))
        self.hist_n = np.zeros((B, L), dtype=np.int64)
        self.trail = np.zeros((3, B, L, TRAIL_CAPACITY))  # x, y, s
        self.trail_n = np.zeros((B, L), dtype=np.int64)
        self.hint = np.full((B, L), np.nan)
        # In-flight messages (latency): per slot, arrival time and sender state, and loss.
        S = self._slots
        self.q_arrival = np.full((S, B, N), np.inf)
        self.q_state = np.zeros((S, 6, B, N))
        self.q_t = np.zeros((S, B, N))
        self.q_lost = np.zeros((S, B, N, N), dtype=bool)
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
        self.gap = np.zeros((B, N - 1))
        self.collided = np.zeros((B, N - 1), dtype=bool)

    # --- API ------------------------------------------------------------------------

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
        obs = self._tick(which)
        self._measure()
        return obs, self._infos()

    def _reset_convoys(self, which: np.ndarray, seeds: Sequence[int | None]) -> None:
        # Per-convoy seeding: a loop over the convoys being reset (episode starts only).
        for b in np.flatnonzero(which):
            s = seeds[b]
            if s is not None:
                self._seed_seqs[b] = np.random.SeedSequence(s)
            elif self._seed_seqs[b] is None:
                self._seed_seqs[b] = np.random.SeedSequence()
            ss_channel = self._seed_seqs[b].spawn(4)[0]
            rng = np.random.default_rng(ss_channel)
            self.keys[b] = np.uint64(int(rng.integers(2**63)))
            if self._ge is not None:
                self._reset_ge(b, rng)
        init = self.scenario.initial_state()
        p = self.plant
        if which.all():
            B = self.num_envs
            p.reset(
                np.tile(init.x, B),
                np.tile(init.y, B),
                np.tile(init.heading, B),
                np.tile(init.speed, B),
            )
        else:
            self._reset_plant_rows(which, init)
        self.leader.reset(which)
        w = which
        self.t[w] = 0.0
        self.step_count[w] = 0
        for arr, value in (
            (self.next_check, -np.inf),
            (self.msgs_sent, 0),
            (self.broadcasts, 0),
            (self.delivered_to, 0),
            (self.lost_to, 0),
            (self.msgs_kept, 0),
            (self.hist_n, 0),
            (self.trail_n, 0),
            (self.hint, np.nan),
            (self.modes, COOP),
            (self.cmd_v, 0.0),
            (self.cmd_dh, 0.0),
            (self.estopped, False),
            (self.policy_failed, False),
            (self.policy_errors, 0),
        ):
            arr[w] = value
        self.last_sent[:, w] = np.nan
        self.q_arrival[:, w] = np.inf
        self._has_cmd[w] = False

    def _reset_ge(self, b: int, rng: np.random.Generator) -> None:
        """Convoy ``b``'s Gilbert-Elliott links as ``Channel.reset`` makes them: one seed
        per ordered link from the channel's generator, the chain's key from that seed."""
        N = self.n_vehicles
        seeds = rng.integers(2**63, size=N * (N - 1)).tolist()
        keys = np.zeros((N, N), dtype=np.uint64)
        pairs = [(s, r) for s in range(N) for r in range(N) if r != s]
        for (s, r), seed in zip(pairs, seeds):
            keys[s, r] = np.uint64(int(np.random.default_rng(seed).integers(2**63)))
        ge = self._ge
        assert ge is not None
        p_bad = ge.mean_bad_s / (self._ge_good[b] + ge.mean_bad_s)
        self.ge_key[b] = keys
        self.ge_bad[b] = counter_uniform_array(keys, GE_INIT) < p_bad
        self.ge_n[b] = 0
        self.ge_t[b] = np.nan

    def _ge_lost(self, send: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``GilbertElliott.lost`` on every link whose sender broadcasts now."""
        ge = self._ge
        assert ge is not None
        N = self.n_vehicles
        offered = send[:, :, None] & ~np.eye(N, dtype=bool)
        n = self.ge_n
        tt = t[:, None, None]
        last = self.ge_t
        offered &= (self._per > 0.0)[:, None, None]  # PER 0: a perfect link, no chain
        step = offered & ~np.isnan(last) & (tt > last)
        a, b = (1.0 / self._ge_good)[:, None, None], 1.0 / ge.mean_bad_s
        p_inf = a / (a + b)
        with np.errstate(invalid="ignore"):
            decay = np.exp(-(a + b) * (tt - last))
        p_bad = p_inf + (np.where(self.ge_bad, 1.0, 0.0) - p_inf) * decay
        moved = counter_uniform_array(self.ge_key, n, GE_ADVANCE) < p_bad
        self.ge_bad = np.where(step, moved, self.ge_bad)
        self.ge_t = np.where(offered, np.where(np.isnan(last), tt, np.fmax(last, tt)), last)
        p = np.where(self.ge_bad, ge.loss_bad, ge.loss_good)
        lost = offered & (p > 0.0) & (counter_uniform_array(self.ge_key, n, GE_LOSS) < p)
        self.ge_n = n + offered
        return lost

    def _reset_plant_rows(self, which: np.ndarray, init: Any) -> None:
        """Reset the plant state of some convoys (``BicyclePlant.reset`` on their rows)."""
        B, N = self.num_envs, self.n_vehicles
        fresh = BicyclePlant(self.presets, self.dt, vectorized=True)
        fresh.reset(init.x, init.y, init.heading, init.speed)
        p = self.plant
        rows = np.flatnonzero(np.repeat(which, N))
        tile = lambda a: np.tile(a, int(which.sum()))  # noqa: E731
        for name in (
            "x",
            "y",
            "heading",
            "speed",
            "accel",
            "yaw_rate",
            "_ramp",
            "_integ",
            "_rate_des",
        ):
            arr = getattr(p, name).copy()
            arr[rows] = tile(getattr(fresh, name))
            setattr(p, name, arr)
        # The setpoint queues are indexed by a shared head: fill every slot of the rows.
        p._queue_v[:, rows] = tile(fresh.speed)[None, :]
        p._queue_h[:, rows] = tile(fresh.heading)[None, :]
        del B

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One tick of every convoy with ``actions`` ``(B, N-1, 2)`` (SI, clipped)."""
        B, N = self.num_envs, self.n_vehicles
        a = np.asarray(actions, dtype=np.float32)
        if a.shape != (B, N - 1, 2):
            raise ValueError(f"actions must have shape {(B, N - 1, 2)}, got {a.shape}")
        t = self.t
        # A non-finite action is a policy error, as in ConvoyEnv (core.tick.decide): the
        # follower stops, the error is counted, and it stays stopped (failsafe) after.
        bad = ~np.isfinite(a).all(axis=-1)
        if bad.any():
            self.policy_errors[:, 1:] += bad
            self.policy_failed[:, 1:] |= bad
            a = np.where(bad[..., None], np.float32(0.0), a)
        a64 = np.clip(a.astype(np.float64), self.action_low, self.action_high)
        a0 = a64[..., 0].astype(np.float32).astype(np.float64)
        a1 = a64[..., 1].astype(np.float32).astype(np.float64)
        v, dh, mode = self._supervise(a0, a1, t)
        cmd_v, cmd_dh = self.cmd_v, self.cmd_dh
        cmd_v[:, 1:], cmd_dh[:, 1:] = v, dh
        self.modes[:, 1:] = mode
        failed = self.policy_failed[:, 1:]
        if failed.any():
            cmd_v[:, 1:] = np.where(failed, 0.0, cmd_v[:, 1:])
            cmd_dh[:, 1:] = np.where(failed, 0.0, cmd_dh[:, 1:])
            self.modes[:, 1:] = np.where(failed, FAILSAFE, self.modes[:, 1:])
        if self.emergency_stop:
            self._emergency(t)
        X, Y, V, H, A, _ = self.own_truth
        v0, h0 = self.leader.command(t, X[:, 0], Y[:, 0], H[:, 0], V[:, 0])
        cmd_v[:, 0] = v0
        cmd_dh[:, 0] = _wrap(h0 - H[:, 0])
        if self.faults:
            self._apply_faults(t)
        self._has_cmd[:] = True
        self._row_cmd = (cmd_v.copy(), cmd_dh.copy(), self.modes.copy())
        self.plant.step(cmd_v.ravel(), (H + cmd_dh).ravel())
        self.step_count += 1
        self.t = self.step_count * self.dt
        A_old = A
        obs = self._tick(np.ones(B, dtype=bool))
        self._measure()
        A_new, YR_new = self.own_truth[4], self.own_truth[5]
        jerk = (A_new[:, 1:] - A_old[:, 1:]) * (1.0 / self.dt)
        rewards = self._reward(
            self.gap - self.desired_gap[:, 1:], A_new[:, 1:], jerk, YR_new[:, 1:]
        )
        terminated = self.collided.any(axis=1)
        truncated = (self.step_count >= self.max_steps) & ~terminated
        infos = self._infos()
        done = terminated | truncated
        if self.autoreset and done.any():
            infos["final_observation"] = obs.copy()
            kept = [
                a.copy()
                for a in (
                    self.hint,
                    self.desired_gap,
                    self.spacing_error,
                    self.pred_age,
                    self.pred_est,
                )
            ]
            self._reset_convoys(done, [None] * B)
            fresh = self._tick(done)
            live = ~done
            for arr, old in zip(
                (self.hint, self.desired_gap, self.spacing_error, self.pred_age, self.pred_est),
                kept,
            ):
                arr[..., live, :] = old[..., live, :]
            obs[done] = fresh[done]
            self._measure()
        return obs, rewards, terminated, truncated, infos

    # --- the member, batched ----------------------------------------------------------

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
