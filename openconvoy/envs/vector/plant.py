"""The batched plant: ``BicyclePlant``'s equations for every vehicle of every convoy.

``VectorPlant`` takes its parameters from a ``BicyclePlant`` (one derivation of the
presets' columns) and steps all vehicles in one compiled loop, the same arithmetic as
``BicyclePlant.step`` vehicle by vehicle. State rows of ``state`` (6, n): x, y (m, ENU),
speed (m/s), heading (rad), accel (m/s²), yaw rate (rad/s), then the heading's cosine and
sine (``COS_H``, ``SIN_H``): libm's, computed once per vehicle and tick where the heading
changes, for every kernel that needs them (the ego frame, the broadcast, the emergency
rule) instead of once per reader.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from openconvoy.envs import plant
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules
from openconvoy.envs.vector.math import wrap
from openconvoy.envs.vehicles import VehiclePreset

X, Y, SPEED, HEADING, ACCEL, YAW_RATE, COS_H, SIN_H = range(8)
ROWS = 8
"""Rows of ``VectorPlant.state``."""
rules(plant, "lag_speed_change", "pi_speed_loop", "slewed_yaw_rate")
_PARAMS = (
    "_tau_v", "_tau_h", "_acc", "_dec", "_rate", "_vmax", "_kappa", "_kp", "_ki", "_ff",
    "_tau_d", "_drag", "_stop", "_brk", "_yaw_acc", "_alat",
)  # fmt: skip
TAU_V, TAU_H, ACC, DEC, RATE, VMAX, KAPPA, KP, KI, FF, TAU_D, DRAG, STOP, BRK, YAW_ACC, ALAT = (
    range(len(_PARAMS))
)


class VectorPlant:
    """``n`` vehicles (convoy-major: vehicle ``i`` of convoy ``b`` is row ``b * N + i``)."""

    def __init__(self, presets: Sequence[VehiclePreset], dt: float) -> None:
        ref = BicyclePlant(presets, dt, vectorized=True)
        self.dt = dt
        self.n = n = len(ref)
        self.params = np.stack([np.asarray(getattr(ref, p), dtype=float) for p in _PARAMS])
        self.pi = ref._pi.copy()
        self.pi_sub = ref._pi_sub
        self.delay = ref._delay_steps.astype(np.int64)
        self.sub_n = np.stack([ref._sub_n1, ref._sub_n2]).astype(np.int64)
        self.sub_h = np.stack([ref._sub_h1, ref._sub_h2]).astype(float)
        self.hdelay = ref._hdelay_steps.astype(np.int64)
        self.depth = ref._depth
        self.state = np.zeros((ROWS, n))
        self.state[COS_H] = 1.0
        self.inner = np.zeros((3, n))  # ramped setpoint, PI integrator, slewed yaw rate
        self.queue = np.zeros((2, self.depth, n))  # speed, heading setpoints
        self.head = np.zeros(1, dtype=np.int64)

    x = property(lambda self: self.state[X])
    y = property(lambda self: self.state[Y])
    speed = property(lambda self: self.state[SPEED])
    heading = property(lambda self: self.state[HEADING])
    accel = property(lambda self: self.state[ACCEL])
    yaw_rate = property(lambda self: self.state[YAW_RATE])

    def reset_rows(
        self, rows: np.ndarray, x: np.ndarray, y: np.ndarray, heading: np.ndarray, speed: np.ndarray
    ) -> None:
        """``BicyclePlant.reset`` on ``rows``: placed, inner loops steady at ``speed``,
        every pending setpoint the initial speed and heading."""
        st = self.state
        st[X, rows], st[Y, rows], st[HEADING, rows], st[SPEED, rows] = x, y, heading, speed
        st[ACCEL, rows] = 0.0
        st[YAW_RATE, rows] = 0.0
        v = st[SPEED, rows]
        p = self.params[:, rows]
        self.inner[0, rows] = v
        self.inner[1, rows] = np.where(self.pi[rows], v + p[DRAG] * v * np.abs(v) - p[FF] * v, 0.0)
        self.inner[2, rows] = 0.0
        self.queue[0][:, rows] = v
        self.queue[1][:, rows] = st[HEADING, rows]
        idx = np.asarray(rows)
        _trig_rows(st, (np.flatnonzero(idx) if idx.dtype == bool else idx).astype(np.int64))

    def step(self, cmd_speed: np.ndarray, cmd_turn: np.ndarray) -> None:
        """Advance ``dt`` with setpoints, shape (n,): speed (m/s) and heading as a change
        from the present heading (rad; the setpoint is heading + change)."""
        _plant_step(
            self.state, self.inner, self.queue, self.head, self.params, self.pi, self.pi_sub,
            self.delay, self.sub_n, self.sub_h, self.hdelay, cmd_speed, cmd_turn, self.dt,
        )  # fmt: skip


@bare_kernel
def _trig_rows(st, rows):  # pragma: no cover - compiled
    """The heading's cosine and sine of vehicles ``rows`` (indices)."""
    for i in rows:
        st[COS_H, i], st[SIN_H, i] = math.cos(st[HEADING, i]), math.sin(st[HEADING, i])


@bare_inline
def _pi_dv(p, i, inner, v_now, v_before, sub_n, sub_h, v0):  # pragma: no cover - compiled
    """``envs.plant.pi_speed_loop`` for vehicle ``i``: the speed change; updates its state
    (``v_before`` acts for ``sub_n[0, i]`` substeps of ``sub_h[0, i]`` s, then ``v_now``
    for ``sub_n[1, i]`` of ``sub_h[1, i]``: ``plant.pi_delay_split``)."""
    gains = (p[KP, i], p[KI, i], p[FF, i], p[TAU_D, i], p[STOP, i], p[DRAG, i])
    substeps = (sub_n[0, i], sub_h[0, i], sub_n[1, i], sub_h[1, i])
    v, inner[0, i], inner[1, i] = plant.pi_speed_loop(
        v_now, v0, inner[0, i], inner[1, i], gains, p[ACC, i], p[DEC, i], p[BRK, i], v_before,
        substeps,
    )  # fmt: skip
    return v - v0


@bare_kernel
def _plant_step(
    st, inner, queue, head_arr, p, pi, n_sub, delay, sub_n, sub_h, hdelay, cmd_v, cmd_h, dt
):  # pragma: no cover - compiled
    depth = queue.shape[1]
    head = head_arr[0]
    for i in range(st.shape[1]):
        queue[0, head, i] = cmd_v[i]
        queue[1, head, i] = st[HEADING, i] + cmd_h[i]
        vmax = p[VMAX, i]
        v_cmd = min(max(queue[0, (head - delay[i]) % depth, i], -vmax), vmax)
        h_cmd = queue[1, (head - hdelay[i]) % depth, i]
        v = st[SPEED, i]
        if pi[i]:
            v_before = min(max(queue[0, (head - delay[i] - 1) % depth, i], -vmax), vmax)
            dv = _pi_dv(p, i, inner, v_cmd, v_before, sub_n, sub_h, v)
        else:
            dv = plant.lag_speed_change(v_cmd, v, p[TAU_V, i], p[ACC, i], p[DEC, i], p[BRK, i], dt)
        v_new = v + dv
        hd = st[HEADING, i]
        err = wrap(h_cmd - hd)
        v_mid = 0.5 * (v + v_new)
        rate, inner[2, i] = plant.slewed_yaw_rate(
            err, v_mid, inner[2, i], p[TAU_H, i], p[RATE, i], p[KAPPA, i], p[YAW_ACC, i],
            p[ALAT, i], dt,
        )  # fmt: skip
        h_mid = hd + 0.5 * rate * dt
        st[X, i] = st[X, i] + v_mid * math.cos(h_mid) * dt
        st[Y, i] = st[Y, i] + v_mid * math.sin(h_mid) * dt
        h_new = wrap(hd + rate * dt)
        st[HEADING, i] = h_new
        st[COS_H, i], st[SIN_H, i] = math.cos(h_new), math.sin(h_new)
        st[ACCEL, i] = dv / dt
        st[YAW_RATE, i] = rate
        st[SPEED, i] = v_new
    head_arr[0] = (head + 1) % depth
