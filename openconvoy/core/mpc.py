"""Distributed longitudinal MPC for one follower: the prediction model and the dense QP.

Pure construction (numpy only) plus a thin call into a QP solver: DAQP (dense active set,
small C; the default) or OSQP's direct API (sparse ADMM; the alternative for long
horizons). No modelling layer in the control loop. The formulation with units is in
``docs/mpc.md``; in short, at every control tick the ego solves, over ``horizon`` steps of
``step_s`` seconds,

    minimise   Σ_k  w_k [ Σ_j w_gap ω_j e_jk² + w_speed (v^p_k − v_k)² + w_accel a_k² ]
             + Σ_k  w_du (u_k − u_{k−1})² + w_slack Σ (s² + s)
    subject to 0 ≤ u_k ≤ v_max                     (speed setpoints, m/s: hard)
               0 − s ≤ v_k ≤ v_max + s             (predicted speed, m/s)
               −decel − s ≤ a_k ≤ accel + s        (predicted acceleration, m/s²)
               gap_k − L ≥ margin + reaction·c_k + c̄_k (2c_k − c̄_k)/(2·decel) − s_k
                                                   (braking-safe gap to the predecessor)
               [hard terminal: e_1H = 0, v_H = v^p_H]

where ``u`` is the speed setpoint the autopilot receives (the action), ``v``, ``a`` the
ego's predicted speed and acceleration from the vehicle's own speed-loop model (``lag``:
first-order lag; ``pi``: the autopilot's PI speed loop with its drive lag), ``e_jk`` the
spacing error to predecessor ``j`` (predicted gap − desired gap at the predicted speed)
weighed by its ``Target.weight`` ``ω_j`` (the policy gives the immediate predecessor 1,
farther ones 0.5), ``v^p`` the immediate predecessor's predicted speed (its shared plan, or constant
velocity), ``c_k = v_k − v^p_k`` the closing speed (linearised about the last plan's
``c̄_k``), ``w_k`` 1 except ``w_terminal`` at the last step (the soft terminal cost), and
``s, s_k ≥ 0`` slacks that keep every state constraint feasible (one for the speed and
acceleration rows, one per gap row, so each step's gap counts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from openconvoy.core.config import Range
from openconvoy.core.errors import ConfigError, DependencyMissing

SOLVERS = ("daqp", "osqp")
TERMINALS = ("soft", "hard")
PLAN_FALLBACKS = ("shift", "constant-velocity")
STATE_SLACK_FACTOR = 1000.0
"""How much more the speed/acceleration rows' slack costs than a gap row's."""


@dataclass(frozen=True)
class PlantModel:
    """The prediction model: a vehicle preset's speed loop (the numbers ``fit-plant`` fits;
    ``envs.vehicles.VehiclePreset`` has the same field names), SI units."""

    speed_loop: str = "lag"
    speed_lag_s: Annotated[float, Range(0.0, 10.0)] = 0.3
    accel_max_mps2: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 1.0
    decel_max_mps2: Annotated[float, Range(0.0, 50.0, lo_open=True)] = 1.0
    actuation_delay_s: Annotated[float, Range(0.0, 2.0)] = 0.1
    max_speed_mps: Annotated[float, Range(0.0, 100.0, lo_open=True)] = 5.0
    speed_kp: Annotated[float, Range(0.0, 100.0)] = 0.0
    speed_ki: Annotated[float, Range(0.0, 100.0)] = 0.0
    speed_ff: Annotated[float, Range(0.0, 10.0)] = 1.0
    drive_lag_s: Annotated[float, Range(0.0, 10.0)] = 0.5
    length_m: Annotated[float, Range(0.0, 50.0)] = 0.779

    def __post_init__(self) -> None:
        if self.speed_loop not in ("lag", "pi"):
            raise ConfigError(
                f"mpc model speed_loop must be 'lag' or 'pi', got {self.speed_loop!r}"
            )

    @classmethod
    def of(cls, preset: Any) -> PlantModel:
        """The model of any object carrying a vehicle preset's fields (a ``VehiclePreset``)."""
        names = [f for f in cls.__dataclass_fields__ if f != "length_m"]
        values = {n: getattr(preset, n) for n in names if hasattr(preset, n)}
        if hasattr(preset, "length_m"):
            values["length_m"] = preset.length_m
        return cls(**values)

    def continuous(self) -> tuple[np.ndarray, np.ndarray]:
        """``(A, B)`` of ``ẋ = A x + B u`` with ``x = [position m, speed m/s, (PI integrator
        m/s)]`` and ``u`` the speed setpoint (m/s). Ramps, friction, drag and the stop logic
        are left out (the acceleration constraints stand in for the ramp)."""
        if self.speed_loop == "lag":
            tau = max(self.speed_lag_s, 1e-3)
            a = np.array([[0.0, 1.0], [0.0, -1.0 / tau]])
            b = np.array([0.0, 1.0 / tau])
            return a, b
        td = max(self.drive_lag_s, 1e-3)
        kp, ki, ff = self.speed_kp, self.speed_ki, self.speed_ff
        a = np.array([[0.0, 1.0, 0.0], [0.0, -(kp + 1.0) / td, 1.0 / td], [0.0, -ki, 0.0]])
        b = np.array([0.0, (ff + kp) / td, ki])
        return a, b

    def steady_state(self, speed: float) -> np.ndarray:
        """The state at position 0 holding ``speed`` (m/s) with the setpoint equal to it."""
        if self.speed_loop == "lag":
            return np.array([0.0, speed])
        # drive = ff v + I = v  ->  I = (1 - ff) v
        return np.array([0.0, speed, (1.0 - self.speed_ff) * speed])


@dataclass(frozen=True)
class MPCConfig:
    """The ``mpc`` controller family's parameters (weights per unit squared: 1/m², s²/m²,
    s⁴/m², s²/m²).

    ``model`` is the prediction model; with ``model_from_vehicle`` the world replaces it
    with the vehicle preset's numbers when it binds the policy to a vehicle.
    ``use_plans``: read the predecessors' shared plans (False: state-only, constant
    velocity). ``plan_fallback`` when the newest plan is older than ``plan_fresh_s``:
    ``shift`` (the last plan shifted in time) or ``constant-velocity`` (dead reckoning
    from the newest state)."""

    horizon: Annotated[int, Range(1, 400)] = 20
    step_s: Annotated[float, Range(0.0, 5.0, lo_open=True)] = 0.1
    w_gap: Annotated[float, Range(0.0, 1e6)] = 1.0
    w_speed: Annotated[float, Range(0.0, 1e6)] = 1.0
    w_accel: Annotated[float, Range(0.0, 1e6)] = 0.1
    w_du: Annotated[float, Range(0.0, 1e6)] = 1.0
    w_terminal: Annotated[float, Range(0.0, 1e6)] = 10.0
    w_slack: Annotated[float, Range(0.0, 1e9, lo_open=True)] = 1e4
    terminal: str = "soft"
    safe_gap: bool = True
    safe_margin_m: Annotated[float, Range(0.0, 100.0)] = 0.2
    solver: str = "daqp"
    use_plans: bool = True
    plan_fallback: str = "shift"
    plan_fresh_s: Annotated[float, Range(0.0, 60.0, lo_open=True)] = 0.15
    model_from_vehicle: bool = True
    model: PlantModel = field(default_factory=PlantModel)

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("terminal", self.terminal, TERMINALS),
            ("solver", self.solver, SOLVERS),
            ("plan_fallback", self.plan_fallback, PLAN_FALLBACKS),
        ):
            if value not in allowed:
                raise ConfigError(f"mpc {name} must be one of {', '.join(allowed)}, got {value!r}")


def discretize(a: np.ndarray, b: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation ``(Ad, Bd)`` of ``ẋ = A x + B u`` over ``dt`` (s),
    by the matrix exponential of the augmented matrix (scaling and squaring, Taylor)."""
    n = a.shape[0]
    m = np.zeros((n + 1, n + 1))
    m[:n, :n] = a * dt
    m[:n, n] = b * dt
    e = _expm(m)
    return e[:n, :n], e[:n, n]


def _expm(m: np.ndarray) -> np.ndarray:
    norm = float(np.abs(m).sum(axis=1).max())
    squarings = max(0, int(math.ceil(math.log2(norm))) + 1) if norm > 0.5 else 0
    x = m / (2.0**squarings)
    out = np.eye(m.shape[0])
    term = np.eye(m.shape[0])
    for k in range(1, 20):
        term = term @ x / k
        out = out + term
    for _ in range(squarings):
        out = out @ out
    return out


class Prediction:
    """Condensed prediction over ``horizon`` steps: ``pos = Pp x0 + Gp u``, ``speed = Pv x0
    + Gv u`` (rows k = 1..H), computed once per model and horizon."""

    def __init__(self, model: PlantModel, horizon: int, step_s: float) -> None:
        self.model = model
        self.horizon = h = horizon
        self.step_s = step_s
        a, b = model.continuous()
        ad, bd = discretize(a, b, step_s)
        n = a.shape[0]
        phi = np.zeros((h, n, n))
        gam = np.zeros((h, n, h))
        p = np.eye(n)
        for k in range(h):
            p = ad @ p
            phi[k] = p
        # gam[k][:, j] = Ad^(k-j) Bd for j <= k
        powers = [np.eye(n)]
        for _ in range(h):
            powers.append(ad @ powers[-1])
        for k in range(h):
            for j in range(k + 1):
                gam[k][:, j] = powers[k - j] @ bd
        self.ad, self.bd = ad, bd
        self.Pp, self.Pv = phi[:, 0, :], phi[:, 1, :]
        self.Gp, self.Gv = gam[:, 0, :], gam[:, 1, :]
        # Acceleration rows: (v_k - v_{k-1}) / dt, v_0 the initial speed.
        d = np.eye(h) - np.eye(h, k=-1)
        self.D = d / step_s

    def propagate(self, x0: np.ndarray, u: float, duration_s: float) -> np.ndarray:
        """The state after holding setpoint ``u`` (m/s) for ``duration_s`` (s): the
        actuation delay, during which the commands already sent still act."""
        if duration_s <= 0.0:
            return x0
        a, b = self.model.continuous()
        ad, bd = discretize(a, b, duration_s)
        return ad @ x0 + bd * u


@dataclass(frozen=True)
class Target:
    """One predecessor the ego keeps a gap to, over the horizon (arrays of length H):
    ``position`` (m, along the path, ego at 0 now), ``desired0`` (desired gap at the ego's
    current speed ``v_now``, m) and ``dgap_dv`` (how it grows with the ego's speed, s),
    ``weight`` (relative)."""

    position: np.ndarray
    desired0: float
    dgap_dv: float
    weight: float = 1.0


@dataclass
class QP:
    """``min ½ zᵀ H z + fᵀ z`` s.t. ``lower ≤ z ≤ upper`` (first ``n`` rows of the bounds:
    simple bounds), ``blower ≤ A z ≤ bupper``; ``sense`` 5 marks equality rows (DAQP's
    convention). ``z = [u_0 .. u_{H-1}, s, s_1 .. s_H]``: the setpoints, the state rows'
    slack, and one slack per braking-safe-gap row (when there are such rows)."""

    H: np.ndarray
    f: np.ndarray
    A: np.ndarray
    bupper: np.ndarray
    blower: np.ndarray
    sense: np.ndarray


def build_qp(
    config: MPCConfig,
    pred: Prediction,
    x0: np.ndarray,
    v_now: float,
    u_prev: float,
    targets: list[Target],
    pred_speed: np.ndarray,
    pred_length_m: float,
    closing_guess: np.ndarray,
    braking_reaction_s: float,
) -> QP:
    """The dense QP of one solve (see the module doc). ``x0``: the ego's model state once
    the actuation delay has passed; ``targets[0]`` is the immediate predecessor, whose
    speed over the horizon is ``pred_speed`` (m/s)."""
    h = pred.horizon
    m = pred.model
    c = config
    w = np.ones(h)
    w[-1] = c.w_terminal
    vx = pred.Pv @ x0
    px = pred.Pp @ x0
    Gv, Gp = pred.Gv, pred.Gp
    hess = np.zeros((h, h))
    grad = np.zeros(h)
    for t in targets:
        # e = (P_t - px - d0 - g (vx - v_now)) - (Gp + g Gv) u  =  r - M u
        r = t.position - px - t.desired0 - t.dgap_dv * (vx - v_now)
        mm = Gp + t.dgap_dv * Gv
        wt = c.w_gap * t.weight * w
        hess += mm.T @ (wt[:, None] * mm)
        grad -= mm.T @ (wt * r)
    # speed difference to the immediate predecessor
    r = pred_speed - vx
    ws = c.w_speed * w
    hess += Gv.T @ (ws[:, None] * Gv)
    grad -= Gv.T @ (ws * r)
    # acceleration a = D (vx + Gv u) - v0/dt e1
    acc0 = pred.D @ vx
    acc0[0] -= x0[1] / pred.step_s
    ga = pred.D @ Gv
    wa = c.w_accel * w
    hess += ga.T @ (wa[:, None] * ga)
    grad += ga.T @ (wa * acc0)
    # setpoint changes
    dd = np.eye(h) - np.eye(h, k=-1)
    hess += c.w_du * dd.T @ dd
    grad[0] -= c.w_du * u_prev
    gap_rows = c.safe_gap and bool(targets)
    ns = 1 + (h if gap_rows else 0)  # one slack for the state rows, one per gap row
    n = h + ns
    H = np.zeros((n, n))
    H[:h, :h] = 2.0 * hess + 1e-8 * np.eye(h)
    # The speed and acceleration rows are the vehicle's physics: their slack costs
    # STATE_SLACK_FACTOR times more than the gap's, so the gap gives way first.
    H[h:, h:] = 2.0 * c.w_slack * np.eye(ns)
    H[h, h] *= STATE_SLACK_FACTOR
    f = np.zeros(n)
    f[:h] = 2.0 * grad
    f[h:] = c.w_slack
    f[h] *= STATE_SLACK_FACTOR
    rows: list[np.ndarray] = []
    upper: list[np.ndarray] = []
    lower: list[np.ndarray] = []
    inf = 1e30
    state_slack = np.zeros((h, ns))
    state_slack[:, 0] = 1.0
    # v_k - s <= vmax ; v_k + s >= 0
    rows.append(np.hstack([Gv, -state_slack]))
    upper.append(m.max_speed_mps - vx)
    lower.append(np.full(h, -inf))
    rows.append(np.hstack([Gv, state_slack]))
    upper.append(np.full(h, inf))
    lower.append(-vx)
    rows.append(np.hstack([ga, -state_slack]))
    upper.append(m.accel_max_mps2 - acc0)
    lower.append(np.full(h, -inf))
    rows.append(np.hstack([ga, state_slack]))
    upper.append(np.full(h, inf))
    lower.append(-m.decel_max_mps2 - acc0)
    if gap_rows:
        # bumper gap - margin - reaction c - cbar (2c - cbar)/(2 b) + s_k >= 0, c = v - v^p
        cbar = np.maximum(closing_guess, 0.0)
        coef_v = braking_reaction_s + cbar / m.decel_max_mps2  # d(.)/dv of the subtracted part
        t0 = targets[0]
        gap0 = t0.position - px - 0.5 * (m.length_m + pred_length_m)
        closing0 = vx - pred_speed
        const = gap0 - c.safe_margin_m - coef_v * closing0 + cbar * cbar / (2.0 * m.decel_max_mps2)
        # const - (Gp + coef_v Gv) u + s_k >= 0  ->  (Gp + coef_v Gv) u - s_k <= const
        gap_slack = np.zeros((h, ns))
        gap_slack[:, 1:] = np.eye(h)
        rows.append(np.hstack([Gp + coef_v[:, None] * Gv, -gap_slack]))
        upper.append(const)
        lower.append(np.full(h, -inf))
    sense_rows = [np.zeros(len(u), dtype=np.int32) for u in upper]
    if c.terminal == "hard" and targets:
        t0 = targets[0]
        r_end = t0.position[-1] - px[-1] - t0.desired0 - t0.dgap_dv * (vx[-1] - v_now)
        row = np.zeros(n)
        row[:h] = Gp[-1] + t0.dgap_dv * Gv[-1]
        rows.append(row[None, :])
        upper.append(np.array([r_end]))
        lower.append(np.array([r_end]))
        row = np.zeros(n)
        row[:h] = Gv[-1]
        rows.append(row[None, :])
        ve = pred_speed[-1] - vx[-1]
        upper.append(np.array([ve]))
        lower.append(np.array([ve]))
        sense_rows.append(np.full(2, 5, dtype=np.int32))
    bu_simple = np.concatenate([np.full(h, m.max_speed_mps), np.full(ns, inf)])
    bl_simple = np.zeros(n)
    return QP(
        H,
        f,
        np.vstack(rows),
        np.concatenate([bu_simple, *upper]),
        np.concatenate([bl_simple, *lower]),
        np.concatenate([np.zeros(n, dtype=np.int32), *sense_rows]),
    )


@dataclass(frozen=True)
class Solution:
    """A solve: ``z`` (the setpoints then the slack), ``ok`` (an optimum found), the
    solver's ``status`` code and the wall time is the caller's to measure."""

    z: np.ndarray
    ok: bool
    status: int


def solve(qp: QP, solver: str = "daqp") -> Solution:
    """Solve ``qp`` with DAQP or OSQP (imported here: ``DependencyMissing`` names the
    extra when absent)."""
    if solver == "daqp":
        try:
            import daqp
        except ImportError as exc:  # pragma: no cover - the vehicle extra installs it
            raise DependencyMissing(
                "the mpc controller needs daqp: pip install 'openconvoy[vehicle]'"
            ) from exc
        x, _, flag, _ = daqp.solve(
            qp.H, qp.f, qp.A, qp.bupper, qp.blower, qp.sense, iter_limit=2000
        )
        return Solution(np.asarray(x), flag in (1, 2), int(flag))
    return _solve_osqp(qp)


def _solve_osqp(qp: QP) -> Solution:
    try:
        import osqp
        from scipy import sparse
    except ImportError as exc:
        raise DependencyMissing(
            "mpc solver 'osqp' needs osqp and scipy: pip install osqp scipy"
        ) from exc
    n = qp.H.shape[0]
    a = np.vstack([np.eye(n), qp.A])
    lo = np.maximum(qp.blower, -1e30)
    hi = np.minimum(qp.bupper, 1e30)
    prob = osqp.OSQP()
    prob.setup(
        sparse.csc_matrix(np.triu(qp.H)),
        qp.f,
        sparse.csc_matrix(a),
        lo,
        hi,
        verbose=False,
        eps_abs=1e-7,
        eps_rel=1e-7,
        max_iter=200000,
        polishing=True,
    )
    res = prob.solve()
    status = int(res.info.status_val)
    return Solution(np.asarray(res.x, dtype=float), status in (1, 2), status)
