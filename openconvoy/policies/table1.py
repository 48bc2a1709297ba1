"""Table I of the OpenConvoy paper as presets: one per surveyed implementation.

Each row is that paper's spacing policy σ, information-flow topology ρ, communication
trigger τ and controller χ, built from this package's parts. Seven of the eight use a
model-predictive controller: here the ``mpc`` family (``core.mpc``, ``policies.mpc``: dense
QP, DAQP), predicting with the vehicle preset's own speed loop, sharing plans over V2V
where the paper shares predicted trajectories. Lateral control is Stanley everywhere (the
papers are longitudinal only). Every function's docstring cites the paper and lists what is
approximated here and why; ``docs/mpc.md`` has the table.

Common approximations, not repeated below:

- The papers' vehicle models (double integrators, first-order engine lags, nonlinear truck
  models) are replaced by the vehicle preset's speed loop: our action is a speed setpoint
  to an autopilot, not a force or an acceleration.
- Constraints are those of ``core.mpc``: speed, acceleration, and the braking-safe gap of
  ``core.safety`` (linearised), softened with one slack; the papers' own constraint sets
  (fuel maps, robust tubes, chance constraints) are not modelled.
- Event triggers are ``core.gates``' (send when the own state deviates from the others'
  constant-velocity extrapolation of the last message beyond a threshold, or after a
  maximum silence): the papers that trigger on a deviation from the *shared predicted
  trajectory* are approximated by that rule, because τ is evaluated by the member before
  the policy acts and does not see the plan.
- Gaps are arc lengths along the predecessor's trail (the paper's σ), so the presets also
  drive curved tracks.
- Ladder ages: a predecessor silent longer than 3 s (instead of 2 s) is dropped, because a
  shifted plan covers the silence; the ladder itself stays off as in the paper.
"""

from __future__ import annotations

import dataclasses

from openconvoy.core.gates import TriggerConfig
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.member import MemberConfig
from openconvoy.core.mpc import MPCConfig
from openconvoy.core.spacing import SpacingConfig
from openconvoy.policies.classical import ClassicalConfig
from openconvoy.policies.presets import (
    CONSTANT_DISTANCE,
    CTH,
    EVENT,
    PD,
    PERIODIC,
    PRESETS,
    QUADRATIC,
    STANLEY,
)

MPC_LADDER = LadderConfig(enabled=False, degrade_after_s=0.5, stop_after_s=3.0)
"""Targets are dropped after 3 s of silence (a shifted plan covers the gap)."""

PLAN_EVENT = TriggerConfig(
    kind="event", period_s=0.1, threshold_m=0.25, speed_threshold_mps=0.2, max_silence_s=0.2
)
"""Event trigger for plan-sharing rows: deviation 0.25 m / 0.2 m/s, at most 0.2 s silent
(a receiver's estimate of a silent sender turns to braking after 0.5 s: ``core.estimate``)."""


def _row(
    name: str,
    description: str,
    topology: str,
    trigger: TriggerConfig,
    spacing: SpacingConfig,
    mpc: MPCConfig | None,
    rear_weight: float = 0.0,
) -> ClassicalConfig:
    return ClassicalConfig(
        name=name,
        description=description,
        member=MemberConfig(topology=topology, trigger=trigger, spacing=spacing, ladder=MPC_LADDER),
        speed=PD,
        heading=STANLEY,
        speed_limit_mps=40.0,
        control_rate_hz=20.0,
        rear_weight=rear_weight,
        mpc=mpc,
    )


def turri2017() -> ClassicalConfig:
    """V. Turri, B. Besselink, K. H. Johansson, "Cooperative look-ahead control for
    fuel-efficient and safe heavy-duty vehicle platooning", IEEE Trans. Control Systems
    Technology 25(1), 2017.

    Row: constant time headway, predecessor following (each truck receives its
    predecessor's planned trajectory), periodic, MPC tracking that plan with a safety
    constraint. Approximated: the platoon coordinator's fuel-optimal, road-slope-aware
    leader speed profile (top layer) is the scenario's leader; the truck dynamics are the
    vehicle preset's; the safety constraint is ``core.safety``'s braking-safe gap."""
    return _row(
        "turri2017",
        "Turri et al. 2017: CTH, predecessor's planned trajectory (lookahead:1), periodic, MPC with plans",
        "lookahead:1",
        PERIODIC,
        CTH,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


def razzaghpour2023() -> ClassicalConfig:
    """M. Razzaghpour et al., 2023: most likely "Predictive Model-Based and
    Control-Aware Communication Strategies for Cooperative Adaptive Cruise Control", IEEE
    Open Journal of Intelligent Transportation Systems, 2023 (arXiv 2303.08076, M.
    Razzaghpour, S. Shahram, R. Valiente, M. Zaman, Y. P. Fallah).

    Checked against that paper's abstract (2026-12-05; the body and the OpenConvoy
    paper's Table I were not reachable as text here): its trigger is a fully distributed
    event-triggered communication combined with model-based communication — each vehicle
    runs an estimator of the others from the model last communicated, and a vehicle sends
    when the error exceeds a threshold. That is the kind of ``core.gates``' event rule
    used here (send when the own state leaves the others' extrapolation of the last
    message), with a constant-velocity model in place of the paper's communicated model.
    Approximated (not checked, assumed from the PD stand-in it replaces,
    ``platoon-allpred-event``):
    constant distance (the title's CACC suggests a time headway; set ``member.spacing``),
    all predecessors, and an MPC with shared plans as the controller."""
    return _row(
        "razzaghpour2023",
        "Razzaghpour et al. 2023: constant distance, all predecessors, event-triggered, MPC with plans",
        "all-predecessors",
        PLAN_EVENT,
        CONSTANT_DISTANCE,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


def razzaghpour_ecc2022() -> ClassicalConfig:
    """M. Razzaghpour, S. Mosharafian, A. Raftari, J. Mohammadpour Velni, Y. P. Fallah,
    "Impact of information flow topology on safety of tightly-coupled connected and
    automated vehicle platoons utilizing stochastic control", ECC 2022.

    Row: constant distance (tightly coupled), all predecessors (the paper compares IFTs;
    pick another with ``member.topology``), periodic, distributed (stochastic) MPC on
    shared predicted trajectories; on loss the last prediction is shifted in time.
    Approximated: the stochastic MPC's chance constraints are the deterministic
    braking-safe gap with a slack."""
    return _row(
        "razzaghpour-ecc2022",
        "Razzaghpour et al. ECC 2022: constant distance, all predecessors, periodic, MPC with plans (shifted on loss)",
        "all-predecessors",
        PERIODIC,
        CONSTANT_DISTANCE,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


def wijnbergen2021() -> ClassicalConfig:
    """P. Wijnbergen, M. Jeeninga, B. Besselink, "Nonlinear spacing policy based vehicle
    platoon control for local string stability and global traffic flow stability", ECC
    2021.

    Row: nonlinear spacing policy, predecessor following, periodic, a (non-MPC) feedback
    controller — the one row of eight that is not model-predictive. Approximated: the
    paper's nonlinear spacing is our ``quadratic`` policy (standstill + headway·v +
    q·v²), its controller our PD on the spacing error with the predecessor's speed as
    feed-forward."""
    return _row(
        "wijnbergen2021",
        "Wijnbergen et al. 2021: nonlinear (quadratic) spacing, predecessor following, periodic, PD",
        "lookahead:1",
        PERIODIC,
        QUADRATIC,
        None,
    )


def razzaghpour_vtc2021() -> ClassicalConfig:
    """M. Razzaghpour, R. Valiente, M. Zaman, Y. P. Fallah, "Impact of communication loss
    on MPC based cooperative adaptive cruise control and platooning", IEEE VTC2021-Fall.

    Row: constant time headway (CACC), predecessor following, periodic, MPC; on loss the
    predecessor is predicted at constant velocity. Here the plan it shares is read while
    fresh and constant-velocity dead reckoning replaces it on loss
    (``plan_fallback = "constant-velocity"``). Approximated: the paper's platooning variant
    (constant distance) is ``razzaghpour-ecc2022``'s spacing; set ``member.spacing``."""
    return _row(
        "razzaghpour-vtc2021",
        "Razzaghpour et al. VTC 2021: CTH, predecessor following, periodic, MPC, constant-velocity on loss",
        "lookahead:1",
        PERIODIC,
        CTH,
        MPCConfig(use_plans=True, plan_fallback="constant-velocity"),
    )


def wu2021() -> ClassicalConfig:
    """Wu et al., 2021 (distributed MPC platooning with event-triggered communication,
    leader information).

    Not verified: neither this paper's text nor the OpenConvoy paper's Table I was
    reachable here (searched 2026-12-05; the paper could not be identified from "Wu et al.
    2021" alone). Approximated, from the PD stand-in it replaces
    (``platoon-leader-event``): constant distance; leader following (here leader +
    predecessor: the braking-safe gap needs the vehicle ahead); event-triggered with
    ``core.gates``' rule; MPC with shared plans. Check them against Table I when citing."""
    return _row(
        "wu2021",
        "Wu et al. 2021: constant distance, leader + predecessor, event-triggered, MPC with plans",
        "leader-predecessor",
        PLAN_EVENT,
        CONSTANT_DISTANCE,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


def wei2017() -> ClassicalConfig:
    """Wei et al., 2017 (multi-vehicle longitudinal trajectory optimisation with a
    time-headway car-following model).

    Not verified: neither this paper's text nor the OpenConvoy paper's Table I was
    reachable here (searched 2026-12-05). Approximated, from the PD stand-in it replaces
    (``cacc-lookaheadN``): constant time headway, every predecessor
    (lookahead:N), periodic, and a receding-horizon QP in place of the paper's
    horizon optimisation (believed dynamic programming). Check them against Table I when
    citing."""
    return _row(
        "wei2017",
        "Wei et al. 2017: CTH, lookahead:N, periodic, MPC with plans",
        "lookahead:N",
        PERIODIC,
        CTH,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


def wen2019() -> ClassicalConfig:
    """Wen et al., 2019 (CACC with a resource-efficient, event-triggered communication
    mechanism).

    Not verified: neither this paper's text nor the OpenConvoy paper's Table I was
    reachable here (searched 2026-12-05). Approximated, from the PD stand-in it replaces
    (``cacc-lookahead1-event``): constant time headway, predecessor
    following, event-triggered with ``core.gates``' rule, MPC with shared plans. Check
    them against Table I when citing."""
    return _row(
        "wen2019",
        "Wen et al. 2019: CTH, predecessor following, event-triggered, MPC with plans",
        "lookahead:1",
        PLAN_EVENT,
        CTH,
        MPCConfig(use_plans=True, plan_fallback="shift"),
    )


ROWS = (
    turri2017,
    razzaghpour2023,
    razzaghpour_ecc2022,
    wijnbergen2021,
    razzaghpour_vtc2021,
    wu2021,
    wei2017,
    wen2019,
)
"""Table I, in the paper's order."""


def _paper_mpc(name: str, use_plans: bool) -> ClassicalConfig:
    """The paper's configuration (all predecessors, 0.1 s broadcast, 15 m path spacing,
    Stanley 0.2, 5 m/s, 20 Hz) with the ``mpc`` speed controller."""
    base = PRESETS["paper"]
    what = "with shared plans" if use_plans else "state-only (constant velocity)"
    return dataclasses.replace(
        base,
        name=name,
        description=f"paper with distributed MPC (H 20 x 0.1 s, DAQP), {what}",
        member=dataclasses.replace(base.member, ladder=MPC_LADDER),
        mpc=MPCConfig(use_plans=use_plans),
    )


TABLE1_PRESETS: dict[str, ClassicalConfig] = {
    c.name: c
    for c in (
        *(row() for row in ROWS),
        _paper_mpc("paper-mpc", True),
        _paper_mpc("paper-mpc-state", False),
    )
}

__all__ = ["ROWS", "TABLE1_PRESETS", "EVENT"]
