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
from typing import NamedTuple

import numpy as np

from openconvoy.envs import plant
from openconvoy.envs.plant import BicyclePlant
from openconvoy.envs.vector.jit import bare_inline, bare_kernel, rules
from openconvoy.envs.vector.math import wrap
from openconvoy.envs.vehicles import VehiclePreset

X, Y, SPEED, HEADING, ACCEL, YAW_RATE, COS_H, SIN_H = range(8)
ROWS = 8
"""Rows of ``VectorPlant.state``."""
rules(plant, "lag_speed_change", "pi_speed_loop", "friction_speed", "slewed_yaw_rate")
_PARAMS = (
    "_tau_v", "_tau_h", "_acc", "_dec", "_rate", "_vmax", "_kappa", "_kp", "_ki", "_ff",
    "_tau_d", "_drag", "_stop", "_brk", "_yaw_acc", "_alat", "_kin",
)  # fmt: skip
(TAU_V, TAU_H, ACC, DEC, RATE, VMAX, KAPPA, KP, KI, FF, TAU_D, DRAG, STOP, BRK, YAW_ACC, ALAT,
 KIN) = range(len(_PARAMS))  # fmt: skip


@bare_inline
def cos_sin(own, b, i):  # pragma: no cover - compiled
    """Twin of ``ConvoyMember.observation``'s ``math.cos``, ``math.sin`` of the ego's
    heading: cosine and sine of vehicle ``i``'s heading in ``own`` (``ROWS``, convoy ``b``):
    rows ``COS_H`` and ``SIN_H`` where ``own`` has them (a copy of the first six rows, as
    the GPS-noised state, has not), else libm's."""
    if own.shape[0] > SIN_H:
        return own[COS_H, b, i], own[SIN_H, b, i]
    return math.cos(own[HEADING, b, i]), math.sin(own[HEADING, b, i])


RAMP, INTEG, SLEWED = range(3)
"""Rows of ``PlantArrays.inner``: the ramped speed setpoint and the PI integrator (m/s),
the slewed yaw rate (rad/s)."""


class PlantArrays(NamedTuple):
    """The batched plant's state and parameters, for its kernel: ``state`` (``ROWS``, n),
    ``inner`` (``RAMP``..``SLEWED``, n), the setpoint ``queue`` (speed, heading; depth, n)
    and its ``head`` (1,); per vehicle slot ``c`` of a convoy (vehicle ``i`` is slot
    ``i % N``: every convoy's presets are the same, so the constants are stored once, not
    per convoy): ``params`` (``_PARAMS`` rows, N), which slots run the PI speed loop ``pi``
    (N,), the speed and heading delays in steps ``delay``, ``hdelay`` (N,), and the PI
    substeps ``sub_n``, ``sub_h`` (2, N: before and after the delay boundary,
    ``plant.pi_delay_split``)."""

    state: np.ndarray
    inner: np.ndarray
    queue: np.ndarray
    head: np.ndarray
    params: np.ndarray
    pi: np.ndarray
    delay: np.ndarray
    hdelay: np.ndarray
    sub_n: np.ndarray
    sub_h: np.ndarray


class VectorPlant:
    """``B`` convoys of the vehicles ``presets`` (convoy-major: vehicle ``i`` of convoy
    ``b`` is row ``b * N + i``); the presets' constants once (``PlantArrays``)."""

    def __init__(self, presets: Sequence[VehiclePreset], dt: float, B: int = 1) -> None:
        ref = BicyclePlant(presets, dt, vectorized=True)
        self.dt = dt
        self.N = len(ref)
        self.n = n = self.N * B
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
        self.arrays = PlantArrays(
            state=self.state,
            inner=self.inner,
            queue=self.queue,
            head=self.head,
            params=self.params,
            pi=self.pi,
            delay=self.delay,
            hdelay=self.hdelay,
            sub_n=self.sub_n,
            sub_h=self.sub_h,
        )

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
        idx = np.asarray(rows)
        idx = (np.flatnonzero(idx) if idx.dtype == bool else idx).astype(np.int64)
        slot = idx % self.N
        p = self.params[:, slot]
        self.inner[RAMP, rows] = v
        self.inner[INTEG, rows] = np.where(
            self.pi[slot], v + p[DRAG] * v * np.abs(v) - p[FF] * v, 0.0
        )
        self.inner[SLEWED, rows] = 0.0
        self.queue[0][:, rows] = v
        self.queue[1][:, rows] = st[HEADING, rows]
        _trig_rows(st, idx)

    def step(self, cmd_speed: np.ndarray, cmd_turn: np.ndarray) -> None:
        """Advance ``dt`` with setpoints, shape (n,): speed (m/s) and heading as a change
        from the present heading (rad; the setpoint is heading + change)."""
        _plant_step(self.arrays, cmd_speed, cmd_turn, self.dt)


@bare_kernel
def _trig_rows(st, rows):  # pragma: no cover - compiled
    """Twin of ``ConvoyMember.observation``'s ``math.cos``, ``math.sin`` of the heading:
    the heading's cosine and sine of vehicles ``rows`` (indices), laid in rows ``COS_H``,
    ``SIN_H``."""
    for i in rows:
        st[COS_H, i], st[SIN_H, i] = math.cos(st[HEADING, i]), math.sin(st[HEADING, i])


@bare_inline
def _pi_dv(pa, i, c, v_now, v_before, v0):  # pragma: no cover - compiled
    """``envs.plant.pi_speed_loop`` for vehicle ``i`` (slot ``c``) of ``pa``
    (``PlantArrays``): the speed change; updates its inner loop (``v_before`` acts for
    ``sub_n[0, c]`` substeps of ``sub_h[0, c]`` s, then ``v_now`` for ``sub_n[1, c]`` of
    ``sub_h[1, c]``). Property-tested through ``_plant_step``:
    tests/envs/vector/test_twins.py::test_plant_step_is_bicycle_plant_step."""
    p, inner, sub_n, sub_h = pa.params, pa.inner, pa.sub_n, pa.sub_h
    gains = (p[KP, c], p[KI, c], p[FF, c], p[TAU_D, c], p[STOP, c], p[DRAG, c], p[KIN, c])
    substeps = (sub_n[0, c], sub_h[0, c], sub_n[1, c], sub_h[1, c])
    v, inner[RAMP, i], inner[INTEG, i] = plant.pi_speed_loop(
        v_now,
        v0,
        inner[RAMP, i],
        inner[INTEG, i],
        gains,
        p[ACC, c],
        p[DEC, c],
        p[BRK, c],
        v_before,
        substeps,
    )
    return v - v0


@bare_kernel
def _plant_step(pa, cmd_v, cmd_h, dt):  # pragma: no cover - compiled
    """``BicyclePlant.step`` for every vehicle of ``pa`` (``PlantArrays``): setpoints
    ``cmd_v`` (m/s) and ``cmd_h`` (heading change, rad), (n,), through the delays and the
    speed and heading loops; moves ``dt`` (s)."""
    st, inner, queue, p = pa.state, pa.inner, pa.queue, pa.params
    depth = queue.shape[1]
    head = pa.head[0]
    N = p.shape[1]
    # Vehicle i = b * N + c: convoy b, slot c (its constants). The loops run over b and c
    # and the queue's slots wrap by a compare (head < depth, delays + 1 < depth), not a
    # modulo: an integer division per vehicle cost more than the bicycle's arithmetic.
    for i0 in range(0, st.shape[1], N):
        for c in range(N):
            i = i0 + c
            _vehicle_step(pa, st, inner, queue, p, i, c, head, depth, cmd_v, cmd_h, dt)
    pa.head[0] = head + 1 if head + 1 < depth else 0


@bare_inline
def _slot(k, depth):  # pragma: no cover - compiled
    """``k % depth`` for ``-depth <= k < depth`` (a queue slot behind the head)."""
    return k + depth if k < 0 else k


@bare_inline
def _vehicle_step(pa, st, inner, queue, p, i, c, head, depth, cmd_v, cmd_h, dt):  # pragma: no cover
    """``_plant_step`` of vehicle ``i`` (slot ``c`` of its convoy; the queue's ``head``)."""
    delay, hdelay = pa.delay, pa.hdelay
    queue[0, head, i] = cmd_v[i]
    queue[1, head, i] = st[HEADING, i] + cmd_h[i]
    vmax = p[VMAX, c]
    v_cmd = min(max(queue[0, _slot(head - delay[c], depth), i], -vmax), vmax)
    h_cmd = queue[1, _slot(head - hdelay[c], depth), i]
    v = st[SPEED, i]
    if pa.pi[c]:
        v_before = min(max(queue[0, _slot(head - delay[c] - 1, depth), i], -vmax), vmax)
        dv = _pi_dv(pa, i, c, v_cmd, v_before, v)
    else:
        dv = plant.lag_speed_change(v_cmd, v, p[TAU_V, c], p[ACC, c], p[DEC, c], p[BRK, c], dt)
    v_new = v + dv
    hd = st[HEADING, i]
    err = wrap(h_cmd - hd)
    v_mid = 0.5 * (v + v_new)
    rate, inner[SLEWED, i] = plant.slewed_yaw_rate(
        err,
        v_mid,
        inner[SLEWED, i],
        p[TAU_H, c],
        p[RATE, c],
        p[KAPPA, c],
        p[YAW_ACC, c],
        p[ALAT, c],
        dt,
    )
    h_mid = hd + 0.5 * rate * dt
    st[X, i] = st[X, i] + v_mid * math.cos(h_mid) * dt
    st[Y, i] = st[Y, i] + v_mid * math.sin(h_mid) * dt
    h_new = wrap(hd + rate * dt)
    st[HEADING, i] = h_new
    st[COS_H, i], st[SIN_H, i] = math.cos(h_new), math.sin(h_new)
    st[ACCEL, i] = dv / dt
    st[YAW_RATE, i] = rate
    st[SPEED, i] = v_new
