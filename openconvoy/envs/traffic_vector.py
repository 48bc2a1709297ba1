"""Vectorized traffic on straight multi-lane roads: highway-env's IDM/MOBIL, all cars at once.

``VectorRoad`` is a highway-env ``Road`` whose ``act`` and ``step`` compute what every
``IDMVehicle`` on it would (``IDMVehicle.act``: MOBIL lane changes, the lane-keeping
steering law, IDM acceleration; ``Vehicle.step``: the kinematic bicycle, lane update) with
numpy over all vehicles, instead of vehicle by vehicle, and write the results back to the
same highway-env vehicle objects (so collisions, rendering and everything reading them are
unchanged). It applies to one road edge of parallel straight lanes along +x starting at
x = 0 (``highway-cut-in``, ``highway-slow-traffic``) with plain ``IDMVehicle`` traffic
(no routes) and our ``ConvoyVehicle`` s; any other road or vehicle falls back to
``FastRoad`` (highway-env's own per-vehicle code).

Decisions that depend on each other keep highway-env's order: a car's abort of a lane
change looks at the targets of the cars before it in ``road.vehicles``, as in its loop.
The parity test holds trajectories to 1e-9 m of highway-env's own (they agree bit for bit
on this machine: the same operations in the same order, on arrays).
"""

from __future__ import annotations

import numpy as np
from highway_env.utils import wrap_to_pi
from numpy._core.umath import clip as _clip  # np.clip's own ufunc, without its wrapper's overhead

from openconvoy.envs.traffic import (
    ConvoyVehicle,
    FastRoad,
    IDMVehicle,
    ScriptedLaneChanger,
    StraightLane,
    collide,
)

_EPS = 1e-2  # highway_env.utils.not_zero
_VECTOR_TYPES = (IDMVehicle, ScriptedLaneChanger)


def _not_zero(x: np.ndarray) -> np.ndarray:
    return np.where(np.abs(x) > _EPS, x, np.where(x >= 0, _EPS, -_EPS))


class VectorRoad(FastRoad):
    """See the module doc. ``lanes``: the edge's lanes, index = lane id."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._edge = self._straight_edge()
        if self._edge is not None:  # the edge's lanes, fixed for the road's life
            lanes = self._edge[2]
            self._lane_arrays = (
                np.array([ln.start[1] for ln in lanes]),
                np.array([ln.length for ln in lanes]),
                np.array([ln.width / 2 for ln in lanes]),
                np.array([40.0 if ln.speed_limit is None else ln.speed_limit for ln in lanes]),
            )

    def _straight_edge(self) -> tuple[str, str, list[StraightLane]] | None:
        graph = self.network.graph
        if (
            len(graph) != 1
            or self.objects
            or self.neighbour_vehicles_connected_lanes
            or self.record_history
        ):
            return None
        ((_from, tos),) = graph.items()
        if len(tos) != 1:
            return None
        ((_to, lanes),) = tos.items()
        for ln in lanes:
            if (
                type(ln) is not StraightLane
                or ln.start[0] != 0.0
                or ln.direction[0] != 1.0
                or ln.direction[1] != 0.0
                or ln.forbidden
            ):
                return None
        return _from, _to, list(lanes)

    def closest_lane(
        self, hx: float, hy: float, heading: float
    ) -> tuple[tuple, StraightLane] | None:
        """``(lane_index, lane)`` that ``RoadNetwork.get_closest_lane_index`` picks for a
        vehicle at ``(hx, hy)`` (m) with ``heading`` (rad), computed as its
        ``distance_with_heading`` does, lane by lane; None off a straight edge."""
        if self._edge is None:
            return None
        _from, _to, lanes = self._edge
        # Every lane heads along +x, so the heading term is the same for all of them.
        angle = np.abs(wrap_to_pi(heading - lanes[0].heading))
        s = float(hx)
        best, best_d = 0, None
        for k, ln in enumerate(lanes):
            d = abs(float(hy - ln.start[1])) + max(s - ln.length, 0) + max(0 - s, 0) + 1.0 * angle
            if best_d is None or d < best_d:
                best, best_d = k, d
        return (_from, _to, best), lanes[best]

    def _vectorizable_types(self) -> bool:
        """A straight edge, and only convoy vehicles and route-less IDM / scripted traffic?"""
        if self._edge is None:
            return False
        for v in self.vehicles:
            t = type(v)
            if t is not ConvoyVehicle and (t not in _VECTOR_TYPES or v.route):
                return False
        return True

    def _before_lane_end(self, x: np.ndarray, movers: np.ndarray) -> bool:
        """No traffic (``movers``) with x position (``x``, m) at the lane's end, where
        ``follow_road`` would switch lanes?"""
        end = self._edge[2][0].length - self._edge[2][0].VEHICLE_LENGTH / 2
        return not bool((movers & (x > end)).any())

    _eye_n = -1
    _eye: np.ndarray

    def _not_self(self, n: int) -> np.ndarray:
        """(1, n, n): True off the diagonal (a vehicle is not its own neighbour)."""
        if n != self._eye_n:
            self._eye_n, self._eye = n, ~np.eye(n, dtype=bool)[None]
        return self._eye

    _PARAMS = (
        "COMFORT_ACC_MAX",
        "COMFORT_ACC_MIN",
        "DISTANCE_WANTED",
        "TIME_WANTED",
        "DELTA",
        "ACC_MAX",
        "POLITENESS",
        "LANE_CHANGE_MIN_ACC_GAIN",
        "LANE_CHANGE_MAX_BRAKING_IMPOSED",
        "LANE_CHANGE_DELAY",
        "LENGTH",
        "KP_LATERAL",
        "KP_HEADING",
        "MAX_STEERING_ANGLE",
    )
    _param_key: tuple = ()
    _mover_key: tuple = ()
    _mover_const: tuple = ()
    _param_cache: dict = {}

    def _params(self, veh: list) -> dict[str, np.ndarray]:
        """The vehicles' fixed parameters as arrays (read once per set of vehicles)."""
        key = tuple(map(id, veh))
        if key != self._param_key:
            p = {k: np.array([getattr(v, k) for v in veh], dtype=float) for k in self._PARAMS}
            p["traffic"] = np.array([type(v) is not ConvoyVehicle for v in veh])
            p["lc"] = np.array([v.enable_lane_change for v in veh])
            p["hold"] = np.array([type(v) is ScriptedLaneChanger for v in veh])
            p["KP_A"] = np.array([v.KP_A for v in veh], dtype=float)
            self._param_key, self._param_cache, self._param_objs = (
                key,
                p,
                list(veh),
            )  # held: the ids stay theirs
        return dict(self._param_cache)

    # ``idm_accel``: the IDM acceleration (m/s², clipped) of every vehicle at the last
    # vectorized ``act``, by ``id``, which the leader's driver uses (TrafficWorld).

    # --- act -------------------------------------------------------------------------------

    def act(self) -> None:
        self.idm_accel = {}
        veh = self.vehicles
        n = len(veh)
        if not n or not self._vectorizable_types():
            super().act()
            return
        pos = np.array([v.position for v in veh], dtype=float).reshape(n, 2)
        x, y = pos[:, 0], pos[:, 1]
        p = self._params(veh)
        if not self._before_lane_end(x, p["traffic"]):
            super().act()
            return
        _from, _to, lanes = self._edge
        lane_y, lane_len, half_w, limit = self._lane_arrays
        vlen = lanes[0].VEHICLE_LENGTH

        # One pass over the vehicles, one contiguous row per quantity.
        cols = (
            np.array(
                [
                    (
                        v.heading,
                        v.speed,
                        v.lane_index[2],
                        v.target_lane_index[2],
                        v.crashed,
                        v.timer,
                        v.target_speed,
                    )
                    for v in veh
                ],
                dtype=float,
            )
            .reshape(n, 7)
            .T.copy()
        )
        h, sp, tspeed = cols[0], cols[1], cols[6]
        lane, tgt = cols[2].astype(int), cols[3].astype(int)
        crashed = cols[4] != 0.0
        p["timer"] = cols[5]
        traffic, lc = p["traffic"], p["lc"]
        c, s = np.cos(h), np.sin(h)
        vx, vy = sp * c, sp * s
        tlimit = _clip(tspeed, 0, limit[lane])

        # Neighbours on every lane, as Road.neighbour_vehicles finds them (ties: the last
        # equal one ahead, the first equal one behind).
        # All lanes at once: (lane, ego, other) masks.
        on = (
            (np.abs(y[None, :] - lane_y[:, None]) <= half_w[:, None] + 1.0)
            & (-vlen <= x)[None, :]
            & (x[None, :] < lane_len[:, None] + vlen)
        )
        cand = on[:, None, :] & self._not_self(n)
        ge = x[None, :] >= x[:, None]
        ahead, behind = cand & ge, cand & ~ge
        xf = np.where(ahead, x, np.inf)[:, :, ::-1]
        front = np.where(ahead.any(axis=2), n - 1 - np.argmin(xf, axis=2), -1)
        xr = np.where(behind, x, -np.inf)
        rear = np.where(behind.any(axis=2), np.argmax(xr, axis=2), -1)

        def idm(me: np.ndarray, ego: np.ndarray, fr: np.ndarray) -> np.ndarray:
            """IDMVehicle.acceleration with ``me``'s parameters for ``ego`` behind ``fr``
            (index arrays; -1 = none: no ego gives 0, no front the free-road term)."""
            e = np.maximum(ego, 0)
            f = np.maximum(fr, 0)
            amax = p["COMFORT_ACC_MAX"][me]
            acc = amax * (
                1 - np.power(np.maximum(sp[e], 0) / np.abs(_not_zero(tlimit[e])), p["DELTA"][me])
            )
            dv = (vx[e] - vx[f]) * c[e] + (vy[e] - vy[f]) * s[e]
            ab = -amax * p["COMFORT_ACC_MIN"][me]
            d_star = (
                p["DISTANCE_WANTED"][me]
                + sp[e] * p["TIME_WANTED"][me]
                + sp[e] * dv / (2 * np.sqrt(ab))
            )
            inter = amax * np.power(d_star / _not_zero(x[f] - x[e]), 2)
            acc = acc - np.where(fr >= 0, inter, 0.0)
            return np.where(ego >= 0, acc, 0.0)

        idx = np.arange(n)
        act = traffic & ~crashed
        # MOBIL for every car whose timer fires (decisions need positions only).
        fires = act & lc & (lane == tgt) & (p["LANE_CHANGE_DELAY"] < p["timer"])
        moving = np.abs(sp) >= 1
        # The accelerations on the current lane (every car), then MOBIL's six per side for
        # the cars whose timer fires (a few per tick: each fires once per LANE_CHANGE_DELAY).
        fi = np.flatnonzero(fires)
        nf = len(fi)
        me_l, ego_l, fr_l = [idx], [idx], [front[lane, idx]]
        sides = {}
        lane_f, x_f = lane[fi], x[fi]
        for side in (-1, 1):
            cl = lane_f + side
            valid = (cl >= 0) & (cl < len(lanes))
            cl_c = _clip(cl, 0, len(lanes) - 1)
            reach = (
                (np.abs(y[fi] - lane_y[cl_c]) <= 2 * 2 * half_w[cl_c])
                & (0 <= x_f)
                & (x_f < lane_len[cl_c] + vlen)
            )
            sides[side] = valid & reach & moving[fi]
            new_pre, new_fol = front[cl_c, fi], rear[cl_c, fi]
            old_pre, old_fol = front[lane_f, fi], rear[lane_f, fi]
            # new follower before/after, self after/before, old follower before/after
            for ego, fr in (
                (new_fol, new_pre),
                (new_fol, fi),
                (fi, new_pre),
                (fi, old_pre),
                (old_fol, fi),
                (old_fol, old_pre),
            ):
                me_l.append(fi)
                ego_l.append(ego)
                fr_l.append(fr)
        all_a = idm(np.concatenate(me_l), np.concatenate(ego_l), np.concatenate(fr_l))
        acc_lane = all_a[:n]
        mobil = all_a[n:].reshape(12, nf)
        mobil_ok: dict[int, np.ndarray] = {}
        for k, side in enumerate((-1, 1)):
            nf_a, nf_pred_a, self_pred_a, self_a, of_a, of_pred_a = mobil[6 * k : 6 * k + 6]
            jerk = (
                self_pred_a - self_a + p["POLITENESS"][fi] * (nf_pred_a - nf_a + of_pred_a - of_a)
            )
            ok = np.zeros(n, dtype=bool)
            ok[fi] = (
                sides[side]
                & ~(nf_pred_a < -p["LANE_CHANGE_MAX_BRAKING_IMPOSED"][fi])
                & ~(jerk < p["LANE_CHANGE_MIN_ACC_GAIN"][fi])
            )
            mobil_ok[side] = ok

        # Lane-change policy in road order (an abort reads the targets set before it).
        timer = p["timer"].copy()
        lane_l, fires_l = lane.tolist(), fires.tolist()
        ok_l = {side: mobil_ok[side].tolist() for side in (-1, 1)}
        for i in np.flatnonzero(act & lc).tolist():
            if lane_l[i] != tgt[i]:
                mates = (idx != i) & (lane != tgt[i]) & (tgt == tgt[i])
                if mates.any():
                    j = np.flatnonzero(mates)
                    d = x[j] - x[i]
                    dv = (vx[i] - vx[j]) * c[i] + (vy[i] - vy[j]) * s[i]
                    ab = -p["COMFORT_ACC_MAX"][i] * p["COMFORT_ACC_MIN"][i]
                    d_star = (
                        p["DISTANCE_WANTED"][i]
                        + sp[i] * p["TIME_WANTED"][i]
                        + sp[i] * dv / (2 * np.sqrt(ab))
                    )
                    if ((0 < d) & (d < d_star)).any():
                        tgt[i] = lane_l[i]
                continue
            if not fires_l[i]:
                continue
            timer[i] = 0.0
            for side in (-1, 1):
                if ok_l[side][i]:
                    tgt[i] = lane_l[i] + side

        # Steering onto the target lane and IDM on the current (and target) lane.
        lat = y - lane_y[tgt]
        heading_cmd = np.arcsin(_clip(-p["KP_LATERAL"] * lat / _not_zero(sp), -1, 1))
        heading_ref = 0.0 + _clip(heading_cmd, -np.pi / 4, np.pi / 4)
        rate_cmd = p["KP_HEADING"] * (((heading_ref - h) + np.pi) % (2 * np.pi) - np.pi)
        slip = np.arcsin(_clip(p["LENGTH"] / 2 / _not_zero(sp) * rate_cmd, -1, 1))
        steer = _clip(
            np.arctan(2 * np.tan(slip)), -p["MAX_STEERING_ANGLE"], p["MAX_STEERING_ANGLE"]
        )
        steer = _clip(steer, -p["MAX_STEERING_ANGLE"], p["MAX_STEERING_ANGLE"])
        acc = acc_lane
        changing = np.flatnonzero(lane != tgt)
        if len(changing):
            acc = acc.copy()
            acc[changing] = np.minimum(
                acc[changing], idm(changing, changing, front[tgt[changing], changing])
            )
        # A scripted target holds its speed instead (ControlledVehicle.speed_control).
        acc = np.where(p["hold"], p["KP_A"] * (tspeed - sp), acc)
        acc = _clip(acc, -p["ACC_MAX"], p["ACC_MAX"])
        self.idm_accel = dict(
            zip(map(id, veh), _clip(acc_lane, -p["ACC_MAX"], p["ACC_MAX"]).tolist())
        )

        steer_l, acc_l, tgt_l, timer_l = steer.tolist(), acc.tolist(), tgt.tolist(), timer.tolist()
        for i in np.flatnonzero(act).tolist():
            v = veh[i]
            v.timer = timer_l[i]
            if tgt_l[i] != v.target_lane_index[2]:
                v.target_lane_index = (_from, _to, tgt_l[i])
            v.action = {"steering": steer_l[i], "acceleration": acc_l[i]}

    # --- step ------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        if not self._vectorizable_types():
            super().step(dt)
            return
        movers = [v for v in self.vehicles if type(v) is not ConvoyVehicle]
        m = len(movers)
        pos = np.array([v.position for v in movers], dtype=float).reshape(m, 2)
        if not self._before_lane_end(pos[:, 0], np.ones(m, dtype=bool)):
            super().step(dt)
            return
        _from, _to, lanes = self._edge
        if movers:
            self._move(movers, pos, dt, lanes, _from, _to)
        collide(self, dt)

    def _move(
        self, movers: list, pos: np.ndarray, dt: float, lanes: list, _from: str, _to: str
    ) -> None:
        m = len(movers)
        cols = (
            np.array(
                [
                    (
                        v.heading,
                        v.speed,
                        v.crashed,
                        float(v.action["steering"]),
                        float(v.action["acceleration"]),
                    )
                    for v in movers
                ],
                dtype=float,
            )
            .reshape(m, 5)
            .T.copy()
        )
        h, sp, steer, acc = cols[0], cols[1], cols[3], cols[4]
        crashed = cols[2] != 0.0
        key = tuple(map(id, movers))
        if key != self._mover_key:  # fixed per set of vehicles
            self._mover_key, self._mover_objs = key, movers  # held: the ids stay theirs
            self._mover_const = tuple(
                np.array([getattr(v, k) for v in movers], dtype=float)
                for k in ("LENGTH", "MAX_SPEED", "MIN_SPEED")
            )
        length, vmax, vmin = self._mover_const
        impact = [v.impact for v in movers]
        # Vehicle.clip_actions
        steer = np.where(crashed, 0.0, steer)
        acc = np.where(crashed, -1.0 * sp, acc)
        acc = np.where(
            sp > vmax,
            np.minimum(acc, 1.0 * (vmax - sp)),
            np.where(sp < vmin, np.maximum(acc, 1.0 * (vmin - sp)), acc),
        )
        # Vehicle.step
        beta = np.arctan(1 / 2 * np.tan(steer))
        pos[:, 0] += sp * np.cos(h + beta) * dt
        pos[:, 1] += sp * np.sin(h + beta) * dt
        hit_l = [imp is not None for imp in impact]
        for k, was_hit in enumerate(hit_l):
            if was_hit:
                pos[k] += impact[k]
        h_new = h + sp * np.sin(beta) / (length / 2) * dt
        sp_new = sp + acc * dt
        # on_state_update: the closest lane (Road.get_closest_lane_index, parallel lanes).
        lane_y, lane_len = self._lane_arrays[:2]
        s = pos[:, 0:1]
        r = pos[:, 1:2] - lane_y[None, :]
        angle = np.abs(((h_new[:, None] - 0.0) + np.pi) % (2 * np.pi) - np.pi)
        dist = np.abs(r) + np.maximum(s - lane_len[None, :], 0) + np.maximum(0 - s, 0) + 1.0 * angle
        lane_new = np.argmin(dist, axis=1).tolist()
        h_l, sp_l = h_new.tolist(), sp_new.tolist()
        steer_l, acc_l, crashed_l = steer.tolist(), acc.tolist(), crashed.tolist()
        # Each vehicle gets its own row of this tick's fresh array (no copy needed).
        for k, (v, row) in enumerate(zip(movers, pos)):
            v.timer += dt
            v.action["steering"] = steer_l[k]
            v.action["acceleration"] = acc_l[k]
            v.position = row
            v.heading = h_l[k]
            v.speed = sp_l[k]
            if hit_l[k]:
                v.crashed = True
                v.impact = None
            else:
                v.crashed = crashed_l[k]
            li = lane_new[k]
            if li != v.lane_index[2]:
                v.lane_index = (_from, _to, li)
                v.lane = lanes[li]
