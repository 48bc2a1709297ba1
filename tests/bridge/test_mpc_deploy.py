"""``deploy`` with an MPC policy: the runner binds the vehicle's model, sends its plan with
its state and hands the plans heard to the policy (simulated MAVLink vehicles, in-process
V2V bus)."""

from __future__ import annotations

import dataclasses
import time

import pytest
from deploy_harness import make_convoy

from openconvoy.bridge.leaderdrive import LeaderDriving
from openconvoy.core.mpc import MPCConfig, PlantModel
from openconvoy.core.plans import leader_plan
from openconvoy.core.state import VehicleState
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.policies.mpc import MPCPolicy
from openconvoy.testing import wait_until


def test_followers_exchange_plans_and_drive_with_the_mpc(tmp_path):
    c = make_convoy(tmp_path, n=3, policy="paper-mpc")
    try:
        f1, f2 = c.cars[1], c.cars[2]
        wait_until(lambda: f2.runner.exchange.plans.plans.get(1) is not None, 20, "a plan heard")
        wait_until(lambda: f1.vehicle.state().speed > 0.5, 20, "follower 1 moving")
        leaders = f1.runner.exchange.plans.plans.get(0), f2.runner.exchange.plans.plans.get(0)
        heard_at = time.time()
    finally:
        c.stop()
    for car, preset in ((f1, "1/6"), (f2, "1/10")):
        policy = car.runner.policy
        assert isinstance(policy, MPCPolicy) and policy.model == PlantModel.of(
            vehicle_preset(preset)
        )
        assert policy.solves > 0 and policy.fallbacks == 0
    plan = f2.runner.exchange.plans.plans[1]
    assert plan.vehicle_id == 1 and len(plan.speeds) == 21 and max(plan.speeds) > 0.0
    # the driven leader shares its driver's plan (as in sim); rho keeps no follower's for f1
    assert set(f1.runner.exchange.plans.plans) == {0}
    for plan in leaders:  # heard while the leader drove its 1 m/s phase
        assert plan is not None and plan.vehicle_id == 0 and len(plan.speeds) == 21
        assert plan.step_s == 0.1 and abs(plan.t0 - heard_at) < 2.0
        assert plan.tau_s == pytest.approx(vehicle_preset("1/10").speed_lag_s)
        assert 0.0 < max(plan.speeds) <= 1.0 + 1e-9
    assert f2.v2v.counters.plans > 0


def _driving(scenario, **kw) -> LeaderDriving:
    args = dict(is_leader=True, passive=False, commanding=True, duration_s=None, rate_hz=20.0)
    return LeaderDriving(scenario, **{**args, **kw})


def test_a_driven_leader_shares_its_drivers_plan_on_the_shared_clock():
    """The deploy leader's plan is the simulated leader's (``core.plans.leader_plan``) with
    its time of validity moved from the run's clock to the shared (wall) clock; it previews
    the paper profile's step to 2 m/s at 20 s; none before the start, after the scenario,
    when passive or without a preset."""
    preset = vehicle_preset("1/10")
    mpc = MPCConfig()
    scenario = make_scenario("paper")
    reference = make_scenario("paper")
    drive = _driving(scenario, preset=preset)
    t_start, wall0 = 100.0, 1.7e9
    own = VehicleState(vehicle_id=0, t=0.0, x=0.0, y=0.0, speed=1.0, heading=0.0)
    for t in (0.0, 0.05, 19.0):  # the driver's state as the leader drives
        scenario.leader_command(t, 0.0, 0.0, 0.0, 1.0)
        reference.leader_command(t, 0.0, 0.0, 0.0, 1.0)
    plan = drive.plan(own, t_start + 19.0, t_start, wall0 + 19.0, mpc)
    want = leader_plan(reference, preset, 19.0, 1.0, mpc.horizon, mpc.step_s)
    assert want is not None and plan == dataclasses.replace(want, t0=wall0 + 19.0)
    assert plan.speeds[0] == 1.0 and plan.speeds[-1] > 1.3  # the step to 2 m/s, foreseen
    assert all(b >= a for a, b in zip(plan.speeds, plan.speeds[1:]))
    assert drive.plan(own, 5.0, None, wall0, mpc) is None  # waiting to start
    assert _driving(scenario, preset=preset, passive=True).plan(own, 5.0, 0.0, wall0, mpc) is None
    assert _driving(scenario).plan(own, 5.0, 0.0, wall0, mpc) is None  # no preset: no plan
    drive.t_finish = t_start + 30.0  # the scenario is over: it brakes (braking_plan)
    assert drive.plan(own, t_start + 31.0, t_start, wall0, mpc) is None
