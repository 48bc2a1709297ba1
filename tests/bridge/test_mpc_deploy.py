"""``deploy`` with an MPC policy: the runner binds the vehicle's model, sends its plan with
its state and hands the plans heard to the policy (simulated MAVLink vehicles, in-process
V2V bus)."""

from __future__ import annotations

from deploy_harness import make_convoy

from openconvoy.core.mpc import PlantModel
from openconvoy.envs.vehicles import vehicle_preset
from openconvoy.policies.mpc import MPCPolicy
from openconvoy.testing import wait_until


def test_followers_exchange_plans_and_drive_with_the_mpc(tmp_path):
    c = make_convoy(tmp_path, n=3, policy="paper-mpc")
    try:
        f1, f2 = c.cars[1], c.cars[2]
        wait_until(lambda: f2.runner.exchange.plans.plans.get(1) is not None, 20, "a plan heard")
        wait_until(lambda: f1.vehicle.state().speed > 0.5, 20, "follower 1 moving")
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
    # on vehicles the leader's driver shares no plan, and rho keeps no follower's
    assert f1.runner.exchange.plans.plans == {}
    assert f2.v2v.counters.plans > 0
