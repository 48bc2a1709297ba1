"""The leaders' driver, batched: ``PathScenario.leader_command`` for B leaders at once
(the same arithmetic; the path search and pure pursuit compiled, the speed profile an
array function of time s and arc length m)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from openconvoy.core.errors import ConfigError
from openconvoy.envs import scenarios
from openconvoy.envs.scenarios import PathScenario, SpeedProfile, emergency_speed, paper_speed
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules
from openconvoy.envs.vector.math import wrap
from openconvoy.envs.vector.plant import HEADING, SPEED, X, Y

rules(scenarios, "paper_speed", "emergency_speed")

WINDOW_M = 20.0
"""``Path.project``'s search window around the last arc length (m)."""


_KERNEL_PROFILES: dict[SpeedProfile, int] = {paper_speed: 1, emergency_speed: 2}
"""Speed profiles the kernel computes itself (``_profile``); others are called per tick."""


SEG_X, SEG_Y, DIR_X, DIR_Y, SEG_LEN = range(5)
"""Columns of ``LeaderRoad.seg``: a segment's start (m), unit direction and length (m)."""
RAMP_ACCEL, RAMP_DECEL, LOOK_MIN, LOOK_TIME = range(4)
"""Entries of ``LeaderRoad.params``: the speed ramp's limits (m/s²), the pure-pursuit
look-ahead's minimum (m) and time (s)."""


class LeaderRoad(NamedTuple):
    """The leaders' path and driving state, for the kernels: the path's segments ``seg``
    (``SEG_X``..``SEG_LEN``) and the arc length at each start ``seg_s`` (m), ``closed``
    (a loop) and its ``length`` (m); per convoy the arc length ``s`` (m), the ramped
    speed command ``cmd`` (m/s), the time of the last command ``t_last`` (s; NaN: none)
    and the profile's ``target`` (m/s) where ``kind`` is 0 (1: the paper's profile, 2:
    the emergency stop's, computed in the kernel); ``params`` (``RAMP_ACCEL``..)."""

    seg: np.ndarray
    seg_s: np.ndarray
    closed: bool
    length: float
    s: np.ndarray
    cmd: np.ndarray
    t_last: np.ndarray
    target: np.ndarray
    kind: int
    params: np.ndarray


class LeaderDriver:
    """The drivers of ``num_envs`` leaders on ``scenario``'s path."""

    def __init__(self, scenario: PathScenario, num_envs: int) -> None:
        self.sc = sc = scenario
        path = scenario.path
        prof = scenario.speed_profile
        self.kind = _KERNEL_PROFILES.get(prof, 0)
        if self.kind == 0 and not isinstance(prof(0.0, 0.0), (int, float)):
            raise ConfigError("VectorConvoyEnv: the scenario's speed profile must return a number")
        self.profile = np.vectorize(prof, otypes=[float])
        self.target = np.zeros(num_envs)
        self.closed = bool(path.closed)
        self.length = float(path.length)
        self.seg = np.concatenate([path._a, path._seg_dir, path._seg_len[:, None]], axis=1)
        self.seg_s = np.asarray(path._s, dtype=float)
        self.params = np.array(
            [sc.ramp_accel_mps2, sc.ramp_decel_mps2, sc.lookahead_min_m, sc.lookahead_time_s]
        )
        self.s = np.zeros(num_envs)
        self.cmd = np.zeros(num_envs)
        self.t_last = np.full(num_envs, np.nan)
        self.road = LeaderRoad(
            seg=self.seg,
            seg_s=self.seg_s,
            closed=self.closed,
            length=self.length,
            s=self.s,
            cmd=self.cmd,
            t_last=self.t_last,
            target=self.target,
            kind=self.kind,
            params=self.params,
        )

    def reset(self, which: np.ndarray) -> None:
        sc = self.sc
        self.s[which] = sc.leader_start_s % self.length if self.closed else sc.leader_start_s
        self.cmd[which] = float(sc.start_speed_mps)
        self.t_last[which] = np.nan

    def command(
        self, t: np.ndarray, own: np.ndarray, cmd_v: np.ndarray, cmd_dh: np.ndarray
    ) -> None:
        """The leaders' setpoints at ``t`` (B,) from their states ``own[:, :, 0]``: speed
        (m/s) into ``cmd_v[:, 0]``, heading change (rad) into ``cmd_dh[:, 0]``."""
        _project(own, self.road)
        if self.kind == 0:
            self.target[:] = self.profile(t, self.s)
        _drive(t, own, self.road, cmd_v, cmd_dh)


@bare_inline
def _segment(seg_s, n, s):  # pragma: no cover - compiled
    """The segment holding arc length ``s`` (``Path._segment``)."""
    return min(max(np.searchsorted(seg_s, s, side="right") - 1, 0), n - 1)


@bare_kernel
def _project(own, road):  # pragma: no cover - compiled
    """``Path.project`` of each leader near its last arc length; updates ``road.s``."""
    seg, seg_s, closed, length, s_arr = road.seg, road.seg_s, road.closed, road.length, road.s
    n = seg.shape[0]
    x, y = own[X, :, 0], own[Y, :, 0]
    for b in range(len(x)):
        if n == 1:
            u = (x[b] - seg[0, SEG_X]) * seg[0, DIR_X] + (y[b] - seg[0, SEG_Y]) * seg[0, DIR_Y]
            s_arr[b] = min(max(u, 0.0), length)
            continue
        i0, span = 0, n
        if n > 2:
            lo, hi = s_arr[b] - WINDOW_M, s_arr[b] + WINDOW_M
            if closed:
                i0 = _segment(seg_s, n, lo % length)
                span = min((_segment(seg_s, n, hi % length) - i0) % n + 1, n)
            else:
                i0 = _segment(seg_s, n, max(lo, 0.0))
                span = _segment(seg_s, n, min(hi, length)) - i0 + 1
        best, s_best = np.inf, 0.0
        for off in range(span):
            i = (i0 + off) % n if closed else min(i0 + off, n - 1)
            u = (x[b] - seg[i, SEG_X]) * seg[i, DIR_X] + (y[b] - seg[i, SEG_Y]) * seg[i, DIR_Y]
            u = min(max(u, 0.0), seg[i, SEG_LEN])
            px, py = seg[i, SEG_X] + seg[i, DIR_X] * u, seg[i, SEG_Y] + seg[i, DIR_Y] * u
            d = (px - x[b]) ** 2 + (py - y[b]) ** 2
            if d < best:
                best, s_best = d, seg_s[i] + u
        s_arr[b] = s_best % length if closed else s_best


@bare_inline
def _profile(kind, t, s, target):  # pragma: no cover - compiled
    """The built-in speed profiles, compiled (``scenarios.paper_speed``,
    ``emergency_speed``); ``target`` for the others."""
    if kind == 1:
        return scenarios.paper_speed(t, s)
    if kind == 2:
        return scenarios.emergency_speed(t, s)
    return target


@bare_kernel
def _drive(t, own, road, cmd_v, cmd_dh):  # pragma: no cover - compiled
    """Twin of ``PathScenario.leader_command`` (after ``_project``): the speed ramp towards
    the profile and pure pursuit one look-ahead ahead, for every leader on ``road`` (``LeaderRoad``) at ``t`` (B,): setpoints into ``cmd_v[:, 0]`` (m/s)
    and ``cmd_dh[:, 0]`` (rad)."""
    seg, seg_s, closed, length, s_arr = road.seg, road.seg_s, road.closed, road.length, road.s
    kind, target, cmd, t_last, p = road.kind, road.target, road.cmd, road.t_last, road.params
    n = seg.shape[0]
    for b in range(len(t)):
        s = s_arr[b]
        tgt = _profile(kind, t[b], s, target[b])
        if not closed:  # stop at the end of an open road, braking at the leader's limit
            tgt = min(tgt, math.sqrt(2.0 * p[RAMP_DECEL] * max(length - s, 0.0)))
        dt = 0.0 if math.isnan(t_last[b]) else max(t[b] - t_last[b], 0.0)
        t_last[b] = t[b]
        if dt > 0.0:
            cmd[b] = cmd[b] + min(max(tgt - cmd[b], -p[RAMP_DECEL] * dt), p[RAMP_ACCEL] * dt)
        look = max(p[LOOK_MIN], p[LOOK_TIME] * max(own[SPEED, b, 0], 0.0))
        ahead = (s + look) % length if closed else s + look
        if closed:
            ahead = ahead % length
        i = _segment(seg_s, n, ahead)
        u = ahead - seg_s[i]
        tx, ty = seg[i, SEG_X] + seg[i, DIR_X] * u, seg[i, SEG_Y] + seg[i, DIR_Y] * u
        cmd_v[b, 0] = cmd[b]
        cmd_dh[b, 0] = wrap(math.atan2(ty - own[Y, b, 0], tx - own[X, b, 0]) - own[HEADING, b, 0])
