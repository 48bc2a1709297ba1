"""``VectorRoad``'s tick compiled: highway-env's per-vehicle code as numba loops.

Four kernels over ``TrafficState``'s arrays replace ~200 small numpy calls a tick:
``place`` (``ConvoyVehicle.set_state``), ``step`` (``IDMVehicle.step`` for every traffic
car, then the collision pre-filter of ``traffic.touching_pairs``), ``decide``
(``Road.act``: ``IDMVehicle.act`` / ``ScriptedLaneChanger.act`` car by car, in road order)
and ``nearest_in_path`` (``TrafficWorld.in_path``'s search). Each is highway-env's scalar
code written again as a loop: the same operations in the same order on the same IEEE
doubles (no fastmath), so trajectories agree with highway-env's own ``Road`` (the parity
tests allow 1e-9 m over whole scenarios; they agree bit for bit on this machine). Not
always to the bit: ``math.asin``, ``atan`` and ``tan`` are libm's, which numpy's own
routines miss by one ulp on some inputs (here ~9 %, 0.3 %, 0.5 % of uniform draws in
(-1, 1)); the property tests on random roads (``tests/envs/traffic``) allow 1e-12.
``decide`` goes car by car as ``Road.act`` does, so a car's abort of a lane change sees the
targets the cars before it chose this tick.

The kernels are compiled by ``vector.jit.kernel`` (numba, cached on disk); importing this
module without numba raises ``DependencyMissing`` and ``VectorRoad`` uses its numpy code.
Frame and units: highway-env's (m, rad, m/s, s); lanes as ``traffic.state.StraightEdge``.
"""

from __future__ import annotations

import math

import numpy as np

from openconvoy.envs.traffic import state
from openconvoy.envs.traffic.state import (
    AMAX,
    BRAKE,
    DELAY,
    GAIN,
    KP_A,
    KP_HEAD,
    KP_LAT,
    MAX_STEER,
    POLITE,
)
from openconvoy.envs.vector.jit import kernel, rules

rules(state, "closing_speed", "desired_gap", "idm_free", "idm_interaction")

_EPS = 1e-2  # highway_env.utils.not_zero
_PI = math.pi
# Rows of the kinematics table ``decide`` builds (7, n).
_SP, _RATIO, _VX, _VY, _C, _S, _X = range(7)


@kernel
def _not_zero(v: float) -> float:
    """``highway_env.utils.not_zero``: ``v`` kept at least 0.01 away from 0."""
    if abs(v) > _EPS:
        return v
    if v >= 0:
        return _EPS
    return -_EPS


@kernel
def _wrap_to_pi(v: float) -> float:
    """``highway_env.utils.wrap_to_pi``: the angle ``v`` (rad) in [-pi, pi)."""
    return ((v + _PI) % (2 * _PI)) - _PI


@kernel
def _clip(v: float, lo: float, hi: float) -> float:
    """``numpy.clip`` of one float, as highway-env clips (``lo <= hi``)."""
    return min(max(v, lo), hi)


@kernel
def closest_lane(x: float, y: float, h: float, lane_y: np.ndarray, length: float) -> int:
    """``RoadNetwork.get_closest_lane_index`` on a straight edge: the lane with the least
    ``distance_with_heading`` (the first of equal ones)."""
    angle = abs(_wrap_to_pi(h - 0.0))
    best, best_d = 0, np.inf
    for k in range(lane_y.shape[0]):
        d = abs(y - lane_y[k]) + max(x - length, 0.0) + max(0.0 - x, 0.0) + angle
        if d < best_d:
            best, best_d = k, d
    return best


@kernel
def place(rows, hx, hy, hh, hsp, x, y, h, sp, hit, lane, tgt, lane_y, length):
    """``ConvoyVehicle.set_state`` for rows ``rows`` (state ``hx, hy, hh, hsp``)."""
    for i in range(rows.shape[0]):
        k = rows[i]
        x[k], y[k], h[k], sp[k] = hx[i], hy[i], hh[i], hsp[i]
        hit[k] = False
        lane[k] = tgt[k] = closest_lane(x[k], y[k], h[k], lane_y, length)


@kernel
def _move(k, dt, x, y, h, sp, steer, acc, crashed, hit, impact, speed_range, half_len):
    """``Vehicle.step`` of car ``k``: ``clip_actions``, the bicycle over ``dt``, an impact."""
    st, a, v = steer[k], acc[k], sp[k]
    if crashed[k]:  # erratic steering and braking until complete stop
        st, a = 0.0, -1.0 * v
    if v > speed_range[1, k]:
        a = min(a, 1.0 * (speed_range[1, k] - v))
    elif v < speed_range[0, k]:
        a = max(a, 1.0 * (speed_range[0, k] - v))
    steer[k], acc[k] = st, a
    beta = math.atan(1 / 2 * math.tan(st))
    x[k] = x[k] + v * math.cos(h[k] + beta) * dt
    y[k] = y[k] + v * math.sin(h[k] + beta) * dt
    if hit[k]:
        x[k] = x[k] + impact[k, 0]
        y[k] = y[k] + impact[k, 1]
        crashed[k], hit[k] = True, False
    h[k] = h[k] + v * math.sin(beta) / half_len[k] * dt
    sp[k] = v + a * dt


@kernel
def _apart(i, j, x, y, c, s, sp, half, dt) -> bool:
    """``touching_pairs``'s separating-axis test for one pair: apart now and after dt, so
    highway-env's ``utils.are_polygons_intersecting`` finds neither (the property test
    holds both)."""
    ci, si, cj, sj = c[i], s[i], c[j], s[j]
    li, wi, lj, wj = half[i, 0], half[i, 1], half[j, 0], half[j, 1]
    ac, as_ = abs(ci * cj + si * sj), abs(si * cj - ci * sj)
    exts = (
        li + lj * ac + wj * as_,
        wi + lj * as_ + wj * ac,
        lj + li * ac + wi * as_,
        wj + li * as_ + wi * ac,
    )
    axes = ((ci, si), (-si, ci), (cj, sj), (-sj, cj))
    du = sp[i] * ci * dt - sp[j] * cj * dt
    dv = sp[i] * si * dt - sp[j] * sj * dt
    now, later = False, False
    for q in range(4):
        ux, uy = axes[q]
        ext = exts[q]
        proj = (x[j] - x[i]) * ux + (y[j] - y[i]) * uy
        vp = du * ux + dv * uy
        if abs(proj) - ext > 1e-9:
            now = True
        if max(proj - ext - max(vp, 0.0), min(vp, 0.0) - proj - ext) > 1e-9:
            later = True
    return now and later


@kernel
def step(
    movers, dt, x, y, h, sp, c, s, steer, acc, crashed, hit, impact, speed_range, half,
    timer, lane, lane_y, length, reach,
):  # fmt: skip
    """``Road.step`` up to its collision pass: every traffic car in ``movers`` moves ``dt``
    s (``IDMVehicle.step``), then ``c, s`` (cos, sin of every heading) are refreshed and
    the pairs (i < j, row-major) highway-env's ``handle_collisions`` may act on are
    returned, (m, 2), as ``traffic.touching_pairs`` finds them."""
    half_len = half[:, 0]
    for q in range(movers.shape[0]):
        k = movers[q]
        _move(k, dt, x, y, h, sp, steer, acc, crashed, hit, impact, speed_range, half_len)
        lane[k] = closest_lane(x[k], y[k], h[k], lane_y, length)
        timer[k] += dt
    n = x.shape[0]
    for k in range(n):
        c[k], s[k] = math.cos(h[k]), math.sin(h[k])
    out = np.empty((n * (n - 1) // 2, 2), dtype=np.intp)
    m = 0
    for i in range(n):
        r_i = abs(sp[i]) * dt + 1e-6
        for j in range(i + 1, n):
            dx, dy, r = x[i] - x[j], y[i] - y[j], reach[i, j] + r_i
            if dx * dx + dy * dy <= r * r and not _apart(i, j, x, y, c, s, sp, half, dt):
                out[m, 0], out[m, 1] = i, j
                m += 1
    return out[:m]


@kernel
def _front_rear(lane_id, e, x, on):
    """``Road.neighbour_vehicles`` (vehicle e, lane): the last of the nearest at or ahead,
    the first of the nearest behind (-1: none)."""
    s = x[e]
    front, rear, s_front, s_rear = -1, -1, 0.0, 0.0
    for j in range(x.shape[0]):
        if j == e or not on[lane_id, j]:
            continue
        sv = x[j]
        if s <= sv and (front < 0 or sv <= s_front):
            front, s_front = j, sv
        if sv < s and (rear < 0 or sv > s_rear):
            rear, s_rear = j, sv
    return front, rear


@kernel
def _idm(me, e, f, idm_p, kin) -> float:
    """``IDMVehicle.acceleration`` with car ``me``'s parameters for ``e`` behind ``f``
    (-1: none; no ego gives 0, no front the free-road term), m/s²."""
    if e < 0:
        return 0.0
    amax = idm_p[0, me]
    acc = state.idm_free(amax, kin[_RATIO, e], idm_p[1, me])
    if f >= 0:
        d_star = _gap_wanted(me, e, f, idm_p, kin)
        acc -= state.idm_interaction(amax, d_star, _not_zero(kin[_X, f] - kin[_X, e]))
    return acc


@kernel
def _gap_wanted(me, e, f, idm_p, kin) -> float:
    """``IDMVehicle.desired_gap`` (m) with car ``me``'s parameters for ``e`` behind ``f``."""
    dv = state.closing_speed(
        kin[_VX, e], kin[_VY, e], kin[_VX, f], kin[_VY, f], kin[_C, e], kin[_S, e]
    )
    return state.desired_gap(idm_p[2, me], idm_p[3, me], idm_p[4, me], kin[_SP, e], dv)


@kernel
def _mobil(k, side, old_f, old_r, x, on, params, idm_p, kin) -> bool:
    """``IDMVehicle.mobil`` (side lane) for car ``k`` (no route) with its old neighbours."""
    new_p, new_f = _front_rear(side, k, x, on)
    new_f_a = _idm(k, new_f, new_p, idm_p, kin)
    new_f_pred_a = _idm(k, new_f, k, idm_p, kin)
    if new_f_pred_a < -params[BRAKE, k]:
        return False
    self_pred_a = _idm(k, k, new_p, idm_p, kin)
    self_a = _idm(k, k, old_f, idm_p, kin)
    old_f_a = _idm(k, old_r, k, idm_p, kin)
    old_f_pred_a = _idm(k, old_r, old_f, idm_p, kin)
    jerk = (
        self_pred_a - self_a + params[POLITE, k] * (new_f_pred_a - new_f_a + old_f_pred_a - old_f_a)
    )
    return not jerk < params[GAIN, k]


@kernel
def _abort(k, lane, tgt, idm_p, kin) -> None:
    """``IDMVehicle.change_lane_policy`` during a change: give it up when a car changing
    into the same lane (its target as of now in road order) is ahead within the desired
    gap (property-tested in the whole tick, tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    t = tgt[k]
    for j in range(lane.shape[0]):
        if j == k or lane[j] == t or tgt[j] != t:
            continue
        d = kin[_X, j] - kin[_X, k]
        if 0 < d < _gap_wanted(k, k, j, idm_p, kin):
            tgt[k] = lane[k]
            return


@kernel
def _change_lane(k, f, r, x, y, lane, tgt, timer, on, params, idm_p, kin, geo, end) -> None:
    """``IDMVehicle.change_lane_policy`` for car ``k`` (own-lane neighbours ``f``, ``r``;
    ``geo`` as ``decide``'s, ``end``: lane length + VEHICLE_LENGTH, m); property-tested in
    the whole tick (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    if lane[k] != tgt[k]:
        _abort(k, lane, tgt, idm_p, kin)
        return
    if not params[DELAY, k] < timer[k]:
        return
    timer[k] = 0.0
    nl = on.shape[0]
    for side in (lane[k] - 1, lane[k] + 1):
        if side < 0 or side >= nl:
            continue
        if not (abs(y[k] - geo[0, side]) <= geo[1, side] and 0 <= x[k] < end):
            continue
        if abs(kin[_SP, k]) < 1:
            continue
        if _mobil(k, side, f, r, x, on, params, idm_p, kin):
            tgt[k] = side


@kernel
def _steering(k, t, y, h, sp, params, half_len, lane_y) -> float:
    """``ControlledVehicle.steering_control`` onto lane ``t``, clipped (rad)."""
    nz = _not_zero(sp[k])
    lateral_cmd = -params[KP_LAT, k] * (y[k] - lane_y[t])
    heading_cmd = math.asin(_clip(lateral_cmd / nz, -1.0, 1.0))
    heading_ref = 0.0 + _clip(heading_cmd, -_PI / 4, _PI / 4)  # the lane heads along +x
    rate_cmd = params[KP_HEAD, k] * _wrap_to_pi(heading_ref - h[k])
    slip = math.asin(_clip(half_len[k] / nz * rate_cmd, -1.0, 1.0))
    m = params[MAX_STEER, k]
    return _clip(math.atan(2 * math.tan(slip)), -m, m)


@kernel
def _kinematics(x, h, sp, c, s, lane, tspeed, limit) -> np.ndarray:
    """(7, n): speed, IDM's free-road ratio (speed over the target speed clipped to the
    lane's limit, as ``IDMVehicle.acceleration`` takes it), vx, vy, cos h, sin h, x;
    refreshes ``c``, ``s``."""
    n = x.shape[0]
    kin = np.empty((7, n))
    for k in range(n):
        c[k], s[k] = math.cos(h[k]), math.sin(h[k])
        target = _clip(tspeed[k], 0.0, limit[lane[k]])
        kin[_SP, k], kin[_C, k], kin[_S, k], kin[_X, k] = sp[k], c[k], s[k], x[k]
        kin[_RATIO, k] = max(sp[k], 0.0) / abs(_not_zero(target))
        kin[_VX, k], kin[_VY, k] = sp[k] * c[k], sp[k] * s[k]
    return kin


@kernel
def _on_lanes(x, y, geo, length, vlen) -> np.ndarray:
    """(lanes, n): ``AbstractLane.on_lane`` (position, margin=1) of every car on every
    lane."""
    nl, n = geo.shape[1], x.shape[0]
    on = np.empty((nl, n), dtype=np.bool_)
    for k in range(n):
        inside = -vlen <= x[k] < length + vlen
        for lane_id in range(nl):
            on[lane_id, k] = inside and abs(y[k] - geo[0, lane_id]) <= geo[2, lane_id]
    return on


@kernel
def decide(
    x, y, h, sp, c, s, lane, tgt, timer, crashed, tspeed, kind, params, idm_p, half_len,
    geo, limit, length, vlen, steer, acc, idm_out,
) -> bool:  # fmt: skip
    """``Road.act`` on the arrays: every car in road order (``kind``: 0 convoy, 1 IDM
    without lane changes, 2 IDM/MOBIL, 3 scripted) decides ``tgt``, ``timer``, ``steer``,
    ``acc``; ``idm_out`` gets every car's IDM acceleration on its lane, clipped (m/s²).
    ``geo``: per lane (rows) its centre's y, ``is_reachable_from``'s and ``on_lane``'s
    lateral reach (m); ``length``: the lanes' length, ``vlen``: VEHICLE_LENGTH (m). False, with nothing changed, when a traffic car is past ``follow_road``'s lane end
    (the caller runs highway-env's code then). Property-tested against highway-env's
    ``Road.act`` on random roads (tests/envs/traffic/test_traffic_road_twins.py::test_a_tick_is_highway_envs_act_then_step)."""
    n = x.shape[0]
    for k in range(n):
        if kind[k] != 0 and x[k] > length - vlen / 2:
            return False
    kin = _kinematics(x, h, sp, c, s, lane, tspeed, limit)
    on = _on_lanes(x, y, geo, length, vlen)
    for k in range(n):
        f, r = _front_rear(lane[k], k, x, on)
        a = _idm(k, k, f, idm_p, kin)
        amax = params[AMAX, k]
        idm_out[k] = _clip(a, -amax, amax)
        if kind[k] == 0 or crashed[k]:
            continue
        if kind[k] == 3:  # ScriptedLaneChanger: holds its target speed
            a = params[KP_A, k] * (tspeed[k] - sp[k])
        elif kind[k] == 2:
            _change_lane(
                k, f, r, x, y, lane, tgt, timer, on, params, idm_p, kin, geo, length + vlen
            )
        steer[k] = _steering(k, tgt[k], y, h, sp, params, half_len, geo[0])
        if kind[k] != 3 and lane[k] != tgt[k]:
            f2, _ = _front_rear(tgt[k], k, x, on)
            a = min(a, _idm(k, k, f2, idm_p, kin))
        acc[k] = _clip(a, -amax, amax)
    return True


@kernel
def nearest_in_path(n, x, y, sp, c, s, width, max_look, target, rng, rate):
    """``TrafficWorld.in_path`` for convoy cars 0..n-1: into ``target`` the nearest car
    ahead whose body overlaps the corridor of the car's width (-1: none within
    ``max_look`` m), its centre-to-centre range (m) and range rate (m/s). Property-tested
    against the world's own search on highway-env's ``Road``
    (tests/envs/traffic/test_traffic_road_twins.py::test_in_path_on_a_vector_road_is_the_worlds)."""
    for i in range(n):
        best, best_lon = -1, np.inf
        ci, si, hw = c[i], s[i], 0.5 * width[i]
        for j in range(x.shape[0]):
            if j == i:
                continue
            dx, dy = x[j] - x[i], y[j] - y[i]
            lon = dx * ci + dy * si
            if lon > 0.0 and abs(-dx * si + dy * ci) < 0.5 * width[j] + hw and lon < max_look:
                if lon < best_lon:
                    best, best_lon = j, lon
        target[i] = best
        if best < 0:
            continue
        dx, dy = x[best] - x[i], y[best] - y[i]
        r = math.hypot(dx, dy)
        rng[i] = r
        dvx, dvy = sp[best] * c[best] - sp[i] * ci, sp[best] * s[best] - sp[i] * si
        rate[i] = (dx * dvx + dy * dvy) / r if r > 0 else 0.0
