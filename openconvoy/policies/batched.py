"""The classical policy on arrays: ``ClassicalPolicy.act`` for a whole batch at once.

``BatchedClassical(config).act_batch(obs)`` takes observations shaped ``(..., D)`` (for
example ``(B, N-1, D)`` from ``envs.VectorConvoyEnv``) and returns actions ``(..., 2)``,
float32, equal to what one ``ClassicalPolicy`` per row would return for the same
sequence of observations: the same arithmetic in the same order, with each row's PID
integrator kept separately. The per-vehicle ``act`` is unchanged (vehicles use it).

With numba (the ``batched`` extra) the batch runs as one compiled loop over rows
(``policies.batched_jit``, bit-equal to ``act``); without it, as the numpy code here
(~100 array calls per batch, ~6x slower: ~260 µs against ~40 µs for 1,024 x 2 rows),
with the same results.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import EllipsisType, ModuleType

import numpy as np

from openconvoy.core.errors import ConfigError, DependencyMissing
from openconvoy.core.observation import LOOKAHEAD_S, STATE_FEATURES
from openconvoy.core.policy import MAX_HEADING_CHANGE_RAD
from openconvoy.policies.classical import ClassicalConfig

_NF = len(STATE_FEATURES)

_jit: ModuleType | None
try:
    from openconvoy.policies import batched_jit as _jit
except DependencyMissing:  # numba comes with the batched extra; numpy does the same work
    _jit = None


@dataclass
class _Targets:
    """Per-row accumulators of one pass over the targets (arrays of the batch shape)."""

    follower: np.ndarray  # the immediate follower's newest state slot
    lost: np.ndarray
    any_valid: np.ndarray
    have_fresh: np.ndarray
    v_ref: np.ndarray
    fresh_sum: np.ndarray
    fresh_n: np.ndarray
    near_speed: np.ndarray
    near_err: np.ndarray
    near_desired: np.ndarray
    stale_terms: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    @classmethod
    def empty(cls, shape: tuple[int, ...], follower: np.ndarray) -> _Targets:
        def no() -> np.ndarray:
            return np.zeros(shape, dtype=bool)

        def zero() -> np.ndarray:
            return np.zeros(shape)

        return cls(follower, no(), no(), no(), zero(), zero(), zero(), zero(), zero(), zero())


class _Float64Columns:
    """``obs.astype(np.float64)`` column by column, as read: the policy reads ~30 of the
    layout's ~100 features, so converting them all would be most of its work."""

    def __init__(self, obs: np.ndarray) -> None:
        self.obs = obs

    def __getitem__(self, key: tuple[EllipsisType, int]) -> np.ndarray:
        return self.obs[key].astype(np.float64)


class BatchedClassical:
    """The classical policy of ``config`` for a batch of vehicles (rows). ``compiled``:
    act through ``batched_jit``'s kernel (None: when numba is importable)."""

    def __init__(self, config: ClassicalConfig, compiled: bool | None = None) -> None:
        if config.speed.is_plugin or config.heading.is_plugin:
            raise ConfigError(
                "act_batch computes the built-in controllers only; a plug-in speed or heading "
                "controller acts per vehicle (act)"
            )
        self.config = config
        self.layout = config.member.layout
        self.dt = 1.0 / config.control_rate_hz
        self._integral: np.ndarray | None = None
        if compiled and _jit is None:
            raise DependencyMissing(
                "compiled act_batch needs numba: pip install 'openconvoy[batched]'"
            )
        use = _jit is not None if compiled is None else compiled
        self._packed = _jit.pack(config) if use and _jit is not None else None

    @property
    def compiled(self) -> bool:
        """Whether ``act_batch`` runs the compiled kernel."""
        return self._packed is not None

    def reset(self, seed: int | None = None) -> None:
        """Forget every row's controller state."""
        self._integral = None

    def reset_rows(self, rows: np.ndarray) -> None:
        """Forget the state of the rows where ``rows`` (bool, the batch shape) is True
        (convoys that started a new episode)."""
        if self._integral is not None:
            self._integral[rows] = 0.0

    def act_batch(self, observations: np.ndarray) -> np.ndarray:
        """Actions ``(..., 2)`` float32 (SI: speed m/s, heading change rad)."""
        obs = np.asarray(observations, dtype=np.float32)
        if obs.shape[-1] != self.layout.size:
            raise ValueError(
                f"observations have {obs.shape[-1]} features, layout expects {self.layout.size}"
            )
        shape = obs.shape[:-1]
        if self._integral is None or self._integral.shape != shape:
            self._integral = np.zeros(shape)
        if self._packed is not None:
            return self._act_compiled(obs)
        o = _Float64Columns(obs)
        own = o[..., self.layout.own_offset]
        t = self._scan_targets(obs, o)
        speed, integral = self._speed(t, own)
        stop = t.lost | ~t.any_valid
        # The controller's memory resets where it did not run on fresh targets.
        self._integral = np.where(stop | ~t.have_fresh, 0.0, integral)
        heading = self._heading(o, own)
        out = np.empty(shape + (2,), dtype=np.float32)
        out[..., 0] = np.where(stop, 0.0, speed)
        h = np.minimum(np.maximum(heading, -MAX_HEADING_CHANGE_RAD), MAX_HEADING_CHANGE_RAD)
        out[..., 1] = np.where(stop, 0.0, h)
        return out

    def _act_compiled(self, obs: np.ndarray) -> np.ndarray:
        """``act_batch`` as ``batched_jit.act_rows`` over the rows of ``obs``."""
        assert self._packed is not None and self._integral is not None and _jit is not None
        shape = obs.shape[:-1]
        rows = np.ascontiguousarray(obs.reshape(-1, obs.shape[-1]))
        integral = self._integral.reshape(-1)  # a view: the kernel updates it in place
        out = np.empty((rows.shape[0], 2), dtype=np.float32)
        _jit.act_rows(rows, integral, *self._packed, out)
        return out.reshape(shape + (2,))

    def _scan_targets(self, obs: np.ndarray, o: _Float64Columns) -> _Targets:
        """Walk the targets nearest first (predecessors, then the leader), as
        ``ClassicalPolicy`` does, collecting what the speed law needs per row."""
        lay = self.layout
        shape = obs.shape[:-1]
        # As ``act`` compares a float32 age with it (``ClassicalPolicy._stale_after``): the
        # limit rounded to float32, or an age of exactly float32(limit) would count as stale.
        degrade = float(np.float32(self.config.member.fresh_age_s))
        newest = {n: obs[..., lay.slot_offset(n) : lay.slot_offset(n) + _NF] for n in lay.slots}
        leader_dup = np.zeros(shape, dtype=bool)
        for p in lay.targets[1:]:
            leader_dup |= np.all(newest["leader"] == newest[p], axis=-1)
        t = _Targets.empty(shape, newest["follower"])
        for name in (*lay.targets[1:], "leader"):
            t0 = lay.target_offset(name)
            valid = o[..., t0 + 4] > 0.5
            err, speed, desired = o[..., t0 + 2], o[..., t0 + 3], o[..., t0 + 1]
            stale = o[..., lay.slot_offset(name) + 5] > degrade
            heard = o[..., lay.slot_offset(name) + 6] > 0.5
            gone = ~valid & heard
            if name == "leader":
                gone &= ~leader_dup
            t.lost |= gone
            first = valid & ~t.any_valid
            t.v_ref = np.where(first, speed, t.v_ref)
            t.any_valid |= valid
            fresh = valid & ~stale
            t.fresh_sum = t.fresh_sum + np.where(fresh, err, 0.0)
            t.fresh_n += fresh
            first_fresh = fresh & ~t.have_fresh
            t.near_speed = np.where(first_fresh, speed, t.near_speed)
            t.near_err = np.where(first_fresh, err, t.near_err)
            t.near_desired = np.where(first_fresh, desired, t.near_desired)
            t.have_fresh |= fresh
            t.stale_terms.append((valid & stale, err, speed))
        return t

    def _speed(self, t: _Targets, own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The speed setpoint (m/s) and the PID integrator's next value, per row: the
        controller on the mean fresh error, capped by the nearest fresh target's law, lowered
        (never raised) by each stale target's."""
        cfg = self.config
        c = cfg.speed
        with np.errstate(invalid="ignore", divide="ignore"):
            error = t.fresh_sum / t.fresh_n
        if cfg.rear_weight > 0.0:
            f = t.follower
            rear = np.where(
                f[..., 6] < 0.5,
                0.0,
                np.hypot(f[..., 0], f[..., 1]).astype(np.float64) - t.near_desired,
            )
            error = error - cfg.rear_weight * rear
        integral = self._integral
        assert integral is not None
        if c.kind == "pid":
            lim = c.integral_limit
            integral = np.where(
                t.have_fresh,
                np.minimum(np.maximum(integral + error * self.dt, -lim), lim),
                integral,
            )
        de = t.v_ref - own
        pid = t.v_ref + c.kp * error + c.ki * integral + c.kd * de
        cap = t.near_speed + c.kp * t.near_err + c.kd * (t.near_speed - own)
        speed = np.where(t.have_fresh, np.minimum(pid, cap), np.inf)
        for is_stale, e, ts in t.stale_terms:
            limit = np.minimum(
                t.v_ref + c.kp * e + c.kd * (t.v_ref - own), ts + c.kp * e + c.kd * (ts - own)
            )
            speed = np.where(is_stale, np.minimum(speed, limit), speed)
        return np.minimum(np.maximum(speed, 0.0), cfg.speed_limit_mps), integral

    def _heading(self, o: _Float64Columns, own: np.ndarray) -> np.ndarray:
        p = self.layout.path_offset
        h = self.config.heading
        valid = o[..., p + 8] >= 0.5
        if h.kind == "stanley":
            change = o[..., p + 1] + np.arctan2(h.gain * o[..., p], h.softening_mps + np.abs(own))
        else:
            j = int(np.argmin([abs(t - h.lookahead_s) for t in LOOKAHEAD_S]))
            x, y = o[..., p + 2 + 2 * j], o[..., p + 3 + 2 * j]
            change = np.where((x == 0.0) & (y == 0.0), 0.0, np.arctan2(y, x))
        return np.where(valid, change, 0.0)
