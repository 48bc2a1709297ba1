"""highway-env's ``IDMVehicle.act`` for every vehicle of a ``TrafficState`` at once.

What each traffic car decides, as highway-env's per-vehicle code does (the same
operations in the same order, on arrays): MOBIL lane changes (``change_lane_policy``,
``mobil``), the lane-keeping steering law (``steering_control``) and IDM acceleration
(``acceleration``) on the current and target lane; a scripted car holds its speed
(``speed_control``). Neighbours are ``Road.neighbour_vehicles``'s (ties: the last equal
one ahead, the first equal one behind), searched only for the (lane, vehicle) pairs a tick
needs: every car on its lane, a changing car on its target lane, a car whose lane-change
timer fired on its side lanes. A car's abort of a lane change looks at the
targets of the cars before it in ``road.vehicles``, as in highway-env's loop.
"""

from __future__ import annotations

import numpy as np

try:  # np.clip's ufunc, called directly (np.clip's Python wrapper costs more than the work)
    from numpy._core.umath import clip as _clip  # type: ignore[attr-defined]  # numpy >= 2
except ImportError:  # numpy 1.x, which pyproject allows
    from numpy.core.umath import clip as _clip  # type: ignore[no-redef]

from openconvoy.envs.traffic import state
from openconvoy.envs.traffic.state import (
    AMAX,
    BRAKE,
    DELAY,
    GAIN,
    KP_A,
    KP_HEAD,
    MAX_STEER,
    POLITE,
    TrafficState,
)

_EPS = 1e-2  # highway_env.utils.not_zero
_GHOST_X = 1e300  # "no vehicle": IDM's interaction term behind it rounds to exactly 0
_SIDES = np.array([[-1], [1]])


def _not_zero(x: np.ndarray) -> np.ndarray:
    """``highway_env.utils.not_zero`` of each element: kept at least 0.01 away from 0."""
    return np.where(np.abs(x) > _EPS, x, np.where(x >= 0, _EPS, -_EPS))


def neighbours(
    st: TrafficState, q_lane: np.ndarray, q_ego: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(front, rear)``: for each query, the index of the vehicle ahead of / behind vehicle
    ``q_ego`` on lane ``q_lane`` (-1: none), as ``Road.neighbour_vehicles`` finds them."""
    e, x, n = st.edge, st.x, st.n
    inside = (-e.vlen <= x) & (x < e.length + e.vlen)
    on = (np.abs(st.y - e.lane_y[:, None]) <= e.on_half_w[:, None]) & inside  # (lanes, n)
    onq = on[q_lane]
    ge = x >= x[q_ego][:, None]  # [q, j]: j is not behind the query's vehicle
    ahead = onq & ge & (q_ego[:, None] != st.arange)
    behind = onq & ~ge
    front = n - 1 - np.where(ahead, x, np.inf)[:, ::-1].argmin(axis=1)
    front[~ahead.any(axis=1)] = -1
    rear = np.where(behind, x, -np.inf).argmax(axis=1)
    rear[~behind.any(axis=1)] = -1
    return front, rear


def kinematics(st: TrafficState) -> np.ndarray:
    """(7, n + 1): speed, speed over the target speed clipped to the lane's limit (IDM's
    free-road ratio), vx, vy, cos h, sin h, x; the last column a ghost far ahead that
    index -1 (no vehicle) picks: the inputs of ``IDMVehicle.acceleration``."""
    sp, c, s = st.sp, st.c, st.s
    tlimit = _clip(st.tspeed, 0, st.edge.limit[st.lane])
    ratio = np.maximum(sp, 0) / np.maximum(tlimit, _EPS)  # abs(not_zero(.)) of a speed >= 0
    kin = np.empty((7, st.n + 1))
    kin[:, :-1] = (sp, ratio, sp * c, sp * s, c, s, st.x)
    kin[:, -1] = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0, _GHOST_X)
    return kin


def idm(
    st: TrafficState, kin: np.ndarray, me: np.ndarray, ego: np.ndarray, fr: np.ndarray
) -> np.ndarray:
    """``IDMVehicle.acceleration`` (m/s²) with ``me``'s parameters for ``ego`` behind ``fr``
    (index arrays; -1 = none: no ego gives 0, no front the free-road term; ``kin`` from
    ``kinematics``)."""
    amax, delta, d0, tau, root = st.idm_p[:, me]
    ke, kf = kin[:, ego], kin[:, fr]
    acc = state.idm_free(amax, ke[1], delta)
    d_star = state.desired_gap(
        d0, tau, root, ke[0], state.closing_speed(*ke[2:4], *kf[2:4], *ke[4:6])
    )
    # A front vehicle is never behind: the gap is >= 0 and not_zero is max(gap, eps).
    acc = acc - state.idm_interaction(amax, d_star, np.maximum(kf[6] - ke[6], _EPS))
    return np.where(ego >= 0, acc, 0.0)


def _queries(
    st: TrafficState, fi: np.ndarray, mv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The (lane, vehicle) neighbour queries of a tick: every vehicle on its lane, the cars
    changing lane (``mv``) on their target lane, the cars whose timer fired (``fi``) on the
    lane to their left and right. Also those side lanes (2, nf) and which MOBIL may try
    (None without ``fi``): the queries and the side-lane checks of
    ``IDMVehicle.change_lane_policy`` (property-tested in the whole tick, tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    lane = st.lane
    if not len(fi):
        if not len(mv):
            return lane, st.arange, None, None
        return np.concatenate((lane, st.tgt[mv])), np.concatenate((st.arange, mv)), None, None
    side = lane[fi] + _SIDES  # (2, nf): left, right
    sc = _clip(side, 0, len(st.edge.lanes) - 1)
    xf, e = st.x[fi], st.edge
    possible = (
        (side == sc)
        & (np.abs(st.y[fi] - e.lane_y[sc]) <= e.reach_w[sc])
        & ((0 <= xf) & (xf < e.length + e.vlen) & (np.abs(st.sp[fi]) >= 1))
    )
    q_lane = np.concatenate((lane, st.tgt[mv], sc[0], sc[1]))
    q_ego = np.concatenate((st.arange, mv, fi, fi))
    return q_lane, q_ego, sc, possible


def _mobil_rows(
    front: np.ndarray, rear: np.ndarray, fi: np.ndarray, base: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The IDM queries (me, ego, front) MOBIL needs beyond the neighbour queries' own, per
    side (left, right): the new follower before/after, the old follower after/before. The
    side-lane queries start at row ``base``. Those of ``IDMVehicle.mobil`` (property-tested
    in the whole tick, tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    nf = len(fi)
    np0, np1 = front[base : base + nf], front[base + nf :]
    nf0, nf1 = rear[base : base + nf], rear[base + nf :]
    old_pre, old_fol = front[fi], rear[fi]
    me = np.concatenate((fi,) * 8)
    ego = np.concatenate((nf0, nf0, old_fol, old_fol, nf1, nf1, old_fol, old_fol))
    fr = np.concatenate((np0, fi, fi, old_pre, np1, fi, fi, old_pre))
    return me, ego, fr


def _mobil(
    st: TrafficState, a_lane: np.ndarray, self_pred: np.ndarray, extra: np.ndarray, fi: np.ndarray
) -> np.ndarray:
    """(2, nf): does MOBIL recommend the left / right lane? ``a_lane``: every vehicle's IDM
    on its lane, ``self_pred`` (2, nf): the cars' own on each side, ``extra``: the answers
    to ``_mobil_rows``. ``IDMVehicle.mobil``'s decision (property-tested in the whole tick,
    tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    p = st.params[:, fi]
    q = extra.reshape(2, 4, len(fi))
    nf_a, nf_pred_a, of_a, of_pred_a = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    jerk = self_pred - a_lane[fi] + p[POLITE] * (nf_pred_a - nf_a + of_pred_a - of_a)
    return ~(nf_pred_a < -p[BRAKE]) & ~(jerk < p[GAIN])


def _aborts(
    st: TrafficState, kin: np.ndarray, tgt: np.ndarray, starts: dict[int, int], acting: np.ndarray
) -> None:
    """``change_lane_policy`` in road order: a car changing lane gives up when another car
    changing into the same lane is ahead of it within its IDM desired gap; ``starts``: the
    cars that begin a change this tick (their new targets count from their turn on).
    ``IDMVehicle.change_lane_policy``'s abort (property-tested in the whole tick,
    tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    moving = st.lane != tgt
    changers = (acting & moving).nonzero()[0].tolist()
    if not changers:
        for k, t in starts.items():
            tgt[k] = t
        return
    lane_l, tgt_l = st.lane.tolist(), tgt.tolist()
    mates = sorted(set(np.flatnonzero(moving).tolist()) | set(starts))
    sp, vx, vy, c, s, x = (kin[k].tolist() for k in (0, 2, 3, 4, 5, 6))
    for i in sorted(set(changers) | set(starts)):
        if i in starts:
            tgt_l[i] = starts[i]
            continue
        ti = tgt_l[i]
        _, _, d0, tau, root = st.idm_p[:, i].tolist()
        for j in mates:
            if j == i or lane_l[j] == ti or tgt_l[j] != ti:
                continue
            d = x[j] - x[i]
            dv = state.closing_speed(vx[i], vy[i], vx[j], vy[j], c[i], s[i])
            if 0 < d < state.desired_gap(d0, tau, root, sp[i], dv):
                tgt_l[i] = lane_l[i]
                break
    tgt[:] = tgt_l


def _steering(st: TrafficState, nz_speed: np.ndarray) -> np.ndarray:
    """``ControlledVehicle.steering_control`` onto each vehicle's target lane, clipped
    (rad)."""
    p = st.params
    lat = st.y - st.edge.lane_y[st.tgt]
    heading_cmd = np.arcsin(_clip(st.neg_kp_lat * lat / nz_speed, -1, 1))
    # (highway-env adds the lane's heading, 0.0: that changes no result below.)
    heading_ref = _clip(heading_cmd, -np.pi / 4, np.pi / 4)
    rate_cmd = p[KP_HEAD] * (((heading_ref - st.h) + np.pi) % (2 * np.pi) - np.pi)
    slip = np.arcsin(_clip(st.half[:, 0] / nz_speed * rate_cmd, -1, 1))
    return _clip(np.arctan(2 * np.tan(slip)), st.neg_max_steer, p[MAX_STEER])


def decide(st: TrafficState) -> np.ndarray:
    """Every acting traffic car's decision, into ``st`` (``tgt``, ``timer``, ``steer``,
    ``acc``). Returns every vehicle's IDM acceleration on its lane, clipped (m/s²).
    highway-env's ``Road.act``, property-tested against it on random roads
    (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    n, p, lane = st.n, st.params, st.lane
    st.read_scripts()
    st.trig()
    acting = st.traffic & ~st.crashed
    fi = (acting & st.lc & (lane == st.tgt) & (p[DELAY] < st.timer)).nonzero()[0]
    mv = (lane != st.tgt).nonzero()[0]
    q_lane, q_ego, sc, possible = _queries(st, fi, mv)
    front, rear = neighbours(st, q_lane, q_ego)
    base = n + len(mv)  # the side-lane queries' first row
    me, ego, fr = q_ego, q_ego, front
    if len(fi):
        mq, eq, fq = _mobil_rows(front, rear, fi, base)
        me, ego, fr = np.concatenate((me, mq)), np.concatenate((ego, eq)), np.concatenate((fr, fq))
    kin = kinematics(st)
    a = idm(st, kin, me, ego, fr)
    a_lane = a[:n]
    a_target = a_lane.copy()  # each car's IDM on the lane it will target
    a_target[mv] = a[n:base]
    starts: dict[int, int] = {}
    if sc is not None and possible is not None:
        q = len(q_lane)
        self_pred = a[base:q].reshape(2, len(fi))
        ok = possible & _mobil(st, a_lane, self_pred, a[q:], fi)
        # Both sides pass: the right one, tried last, wins (as in highway-env's loop).
        new = np.where(ok[1], sc[1], np.where(ok[0], sc[0], lane[fi]))
        a_target[fi] = np.where(ok[1], self_pred[1], self_pred[0])
        st.timer[fi] = 0.0
        starts = {k: t for k, t in zip(fi.tolist(), new.tolist()) if t != lane[k]}
    tgt = st.tgt.copy()
    _aborts(st, kin, tgt, starts, acting & st.lc)
    st.tgt = tgt
    acc = np.where(lane != tgt, np.minimum(a_lane, a_target), a_lane)
    acc = np.where(st.hold, p[KP_A] * (st.tspeed - st.sp), acc)
    amax = p[AMAX]
    st.steer = np.where(acting, _steering(st, _not_zero(st.sp)), st.steer)
    st.acc = np.where(acting, _clip(acc, -amax, amax), st.acc)
    return _clip(a_lane, -amax, amax)
