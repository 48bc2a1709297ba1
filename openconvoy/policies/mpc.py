"""The ``mpc`` controller family: distributed MPC on the observation, with shared plans.

``MPCPolicy(config)`` for a ``ClassicalConfig`` whose ``mpc`` is set. Each tick it reads
the targets from the observation (as ``ClassicalPolicy`` does: the same stale and lost
rules), predicts each predecessor over the horizon — from its shared plan
(``core.plans``), or at constant velocity when it has none (state-only) — builds the
dense QP of ``core.mpc`` and solves it with DAQP. The first setpoint is the action's
speed; the predicted speeds are the plan it shares. Lateral control is the classical
Stanley / pure pursuit. When a solve fails the classical χ_v of ``config.speed`` acts
that tick (counted in ``fallbacks``).

The prediction model is the vehicle preset's (``bind_vehicle``; the worlds call it with
each follower's preset) unless ``mpc.model_from_vehicle`` is false.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from openconvoy.core.mpc import MPCConfig, PlantModel, Prediction, Target, build_qp, solve
from openconvoy.core.observation import DERIVED_FEATURES, STATE_FEATURES
from openconvoy.core.plans import Plan, PlanHistory, stitched_distance, stitched_speeds_at
from openconvoy.core.policy import make_action
from openconvoy.core.spacing import speed_gap_m
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy

_NF, _ND = len(STATE_FEATURES), len(DERIVED_FEATURES)
_AGE, _SPD, _HEARD = (STATE_FEATURES.index(n) for n in ("age", "speed", "valid"))
_ARC, _DESIRED, _TSPEED, _VALID = (
    DERIVED_FEATURES.index(n) for n in ("arc_gap", "desired_gap", "speed", "valid")
)


PLAN_MISMATCH_MPS = 1.0
"""A plan whose speed at the newest state's time exceeds that state's by more (m/s) only
lowers the forecast (the slower of it and constant velocity): its sender was overridden."""

PLAN_KEEP_EXTRA_S = 1.0
"""How long (s) past the member's stop age a replaced plan is kept (``PlanHistory``)."""


class MPCPolicy:
    """Implements ``core.policy.Policy`` and ``core.plans.PlanningPolicy``."""

    def __init__(self, config: ClassicalConfig) -> None:
        if config.mpc is None:
            raise ValueError(f"policy {config.name!r} has no [mpc] table")
        self.config = config
        self.mpc: MPCConfig = config.mpc
        self.layout = config.member.layout
        self._classical = ClassicalPolicy(config)
        self.model = self.mpc.model
        self.reaction_s = self.model.actuation_delay_s + self.model.speed_lag_s
        self._prediction = Prediction(self.model, self.mpc.horizon, self.mpc.step_s)
        self.fallbacks = 0
        self.solves = 0
        # Plans are read back to the newest state of their sender, which the member keeps
        # up to its stop age.
        self._history = PlanHistory(config.member.ladder.stop_after_s + PLAN_KEEP_EXTRA_S)
        self.reset()

    # --- ConvoyPolicy ----------------------------------------------------------------

    @property
    def member_config(self) -> Any:
        return self.config.member

    @property
    def control_rate_hz(self) -> float:
        return self.config.control_rate_hz

    @property
    def name(self) -> str:
        return self.config.name

    def reset(self, seed: int | None = None) -> None:
        self._classical.reset(seed)
        self._u_prev: float | None = None
        self._plans: Mapping[int, Plan] = {}
        self._history.clear()
        self._vehicle_id: int | None = None
        self._now: float | None = None
        self._own_plan: Plan | None = None
        self._last_v: np.ndarray | None = None

    def bind_vehicle(self, preset: Any) -> None:
        """Take the prediction model from the vehicle preset (an object with
        ``VehiclePreset``'s fields) when ``mpc.model_from_vehicle``."""
        if not self.mpc.model_from_vehicle:
            return
        self.model = PlantModel.of(preset)
        self.reaction_s = self.model.actuation_delay_s + (
            self.model.speed_lag_s if self.model.speed_loop == "lag" else self.model.drive_lag_s
        )
        self._prediction = Prediction(self.model, self.mpc.horizon, self.mpc.step_s)

    # --- PlanningPolicy --------------------------------------------------------------

    def observe_plans(self, plans: Mapping[int, Plan], vehicle_id: int, now: float) -> None:
        self._plans = plans
        self._history.add(plans, now)
        self._vehicle_id = vehicle_id
        self._now = now

    def plan(self) -> Plan | None:
        return self._own_plan

    # --- the tick --------------------------------------------------------------------

    def act(self, observation: np.ndarray) -> np.ndarray:
        lay = self.layout
        if observation.shape != (lay.size,):
            raise ValueError(
                f"observation has shape {observation.shape}, layout expects ({lay.size},)"
            )
        obs = observation.tolist()
        stale_after = self._classical._stale_after(observation.dtype)
        _, lost = self._classical._targets(obs, stale_after)
        own = obs[lay.own_offset]
        targets = self._read_targets(obs, stale_after)
        if lost or not targets:
            self._u_prev = 0.0
            self._own_plan = None
            return self._classical.act(observation) if not lost else make_action(0.0, 0.0)
        speed = self._solve(own, targets)
        if speed is None:
            self.fallbacks += 1
            action = self._classical.act(observation)
            self._u_prev = float(action[0])
            return action
        speed = min(max(speed, 0.0), self.config.speed_limit_mps)
        self._u_prev = speed
        return make_action(speed, self._classical._heading_change(obs, own))

    def _read_targets(self, obs: list[float], stale_after: float) -> list[dict[str, float]]:
        """Valid targets nearest first: arc gap, desired gap, estimated speed, how many
        pairs ahead (``m``), the newest message's speed and age, and staleness."""
        out = []
        for name, state, target in self._classical._target_slots:
            d = obs[target : target + _ND]
            if d[_VALID] < 0.5:
                continue
            m = int(name.split("_")[1]) if name.startswith("pred_") else 0
            out.append(
                {
                    "arc": d[_ARC],
                    "desired": d[_DESIRED],
                    "speed": d[_TSPEED],
                    "m": float(m),
                    "msg_speed": obs[state + _SPD],
                    "msg_dist": float(np.hypot(obs[state], obs[state + 1])),
                    "age": obs[state + _AGE],
                    "stale": float(obs[state + _AGE] > stale_after),
                }
            )
        if out and self._vehicle_id is not None:
            for t in out:
                if t["m"] == 0.0:
                    t["m"] = float(self._vehicle_id)
        elif out:
            first = out[0]
            for t in out:
                if t["m"] == 0.0:  # the leader, id unknown: pairs ~ the gap ratio
                    t["m"] = max(1.0, round(t["desired"] / max(first["desired"], 1e-6)))
        return out

    def _solve(self, v_now: float, targets: list[dict[str, float]]) -> float | None:
        c, pred = self.mpc, self._prediction
        h, dt = c.horizon, c.step_s
        delay = self.model.actuation_delay_s
        u_prev = v_now if self._u_prev is None else self._u_prev
        x0 = pred.propagate(self.model.steady_state(v_now), u_prev, delay)
        times = delay + dt * np.arange(1, h + 1)  # seconds from now
        spacing = self.config.member.spacing
        qp_targets: list[Target] = []
        pred_speed = np.zeros(h)
        for i, t in enumerate(targets):
            speeds, corr = self._forecast(t, times)
            # Position along the path from now: the gap now plus what the forecast covers.
            steps = np.diff(np.concatenate([[0.0], times]))
            v0 = self._forecast_now(t)
            mids = 0.5 * (speeds + np.concatenate([[v0], speeds[:-1]]))
            position = t["arc"] + corr + np.cumsum(mids * steps)
            dgap = 0.0
            if spacing.kind != "constant-distance":
                dgap = t["m"] * (
                    spacing.headway_s
                    + 2.0
                    * spacing.quadratic_s2_per_m
                    * max(v_now, 0.0)
                    * (spacing.kind == "quadratic")
                )
            qp_targets.append(Target(position, t["desired"], dgap, 1.0 if i == 0 else 0.5))
            if i == 0:
                pred_speed = speeds
        first = targets[0]
        pred_len = self._pred_length(first, v_now)
        closing = (self._last_v if self._last_v is not None else np.full(h, v_now)) - pred_speed
        qp = build_qp(
            c, pred, x0, v_now, u_prev, qp_targets, pred_speed, pred_len, closing, self.reaction_s
        )
        self.solves += 1
        sol = solve(qp, c.solver)
        if not sol.ok or not np.all(np.isfinite(sol.z)):
            self._own_plan = None
            return None
        u = sol.z[:h]
        v = pred.Pv @ x0 + pred.Gv @ u
        self._last_v = np.concatenate([v[1:], v[-1:]])
        if self._now is not None and self._vehicle_id is not None:
            speeds_plan = tuple(float(max(s, 0.0)) for s in np.concatenate([[x0[1]], v]))
            self._own_plan = Plan(
                self._vehicle_id,
                self._now + delay,
                dt,
                speeds_plan,
                self.model.speed_lag_s
                if self.model.speed_loop == "lag"
                else self.model.drive_lag_s,
            )
        return float(u[0])

    def _plans_of(self, t: dict[str, float]) -> list[Plan] | None:
        """The plans to read for target ``t``, oldest first (None: the member's estimate
        at constant velocity). The newest is fresh while its age is within
        ``plan_fresh_s`` (plus the sender's delay, by which its ``t0`` leads); older, the
        plans are read shifted in time (``shift``) or dropped (``constant-velocity``). A
        stale target whose member estimate has it stopped keeps that (safe) estimate."""
        if not self.mpc.use_plans or self._now is None or self._vehicle_id is None:
            return None
        m = int(t["m"])
        vid = self._vehicle_id - m if m < self._vehicle_id else 0
        plan = self._plans.get(vid)
        if plan is None:
            return None
        if t["stale"] > 0.5 and self.mpc.plan_fallback != "shift":
            return None
        fresh = self._now - plan.t0 <= self.mpc.plan_fresh_s
        if not fresh and self.mpc.plan_fallback == "constant-velocity":
            return None
        return self._history.plans(vid) or [plan]

    def _forecast_now(self, t: dict[str, float]) -> float:
        plans = self._plans_of(t)
        if plans is None:
            return t["speed"]
        assert self._now is not None
        return float(stitched_speeds_at(plans, np.array([self._now]))[0])

    def _forecast(self, t: dict[str, float], times: np.ndarray) -> tuple[np.ndarray, float]:
        """Target ``t``'s speeds at ``times`` (s from now) and the correction (m) to its
        gap. The member dead-reckons from the newest message (constant speed while fresh,
        braking once stale: ``core.estimate``), covering ``(v_msg + v_est)/2 · age``; with
        plans, the distance they cover since that message (each instant read from the
        plan newest by then: ``core.plans.stitched_distance``) replaces it."""
        plans = self._plans_of(t)
        if plans is None:
            return np.full(len(times), t["speed"]), 0.0
        assert self._now is not None
        now = self._now
        age = max(t["age"], 0.0)
        ahead = stitched_speeds_at(plans, now + times)
        # A plan well above the newest state (its sender overridden: a stop, a fault, and
        # the braking plan it then shares lost) only lowers the forecast: the slower of
        # the two, from the member's estimate of that state.
        then = float(stitched_speeds_at(plans, np.array([now - age]))[0])
        if then - t["msg_speed"] > PLAN_MISMATCH_MPS:
            return np.minimum(ahead, t["speed"]), 0.0
        # A state newer than every plan (the plans lost, the state heard) is the better
        # word on the speed: the plan is read anchored to it, its shape kept.
        offset = t["msg_speed"] - then if now - age > plans[-1].t0 else 0.0
        ahead = np.maximum(ahead + offset, 0.0)
        if t["speed"] > 0.0 or t["msg_speed"] <= 0.0:
            member_d = 0.5 * (t["msg_speed"] + t["speed"]) * age
        else:  # stopped by the braking estimate: how far it went is the gap's excess
            member_d = min(max(t["arc"] - t["msg_dist"], 0.0), t["msg_speed"] * age)
        covered = stitched_distance(plans, now - age, now) + offset * age
        corr = covered - member_d if age > 0.0 else 0.0
        return ahead, corr

    def _pred_length(self, first: dict[str, float], v_now: float) -> float:
        """The predecessor's length (m): from the desired gap's half lengths where the
        spacing policy adds them (``core.spacing``), else the ego's."""
        s = self.config.member.spacing
        if s.kind == "constant-distance" or first["m"] != 1.0:
            return self.model.length_m
        base = speed_gap_m(s.code, v_now, s.standstill_m, s.headway_s, s.quadratic_s2_per_m)
        halves = first["desired"] - base
        return max(2.0 * halves - self.model.length_m, 0.0)


def mpc_config(config: ClassicalConfig, **changes: Any) -> ClassicalConfig:
    """``config`` with its ``mpc`` table changed (``MPCConfig`` field names)."""
    assert config.mpc is not None
    return dataclasses.replace(config, mpc=dataclasses.replace(config.mpc, **changes))


def is_mpc(config: ClassicalConfig) -> bool:
    return config.mpc is not None


__all__ = ["MPCPolicy", "mpc_config", "is_mpc"]
