"""``forge`` faults in VectorConvoyEnv against ConvoyEnv (``_compare`` of
``test_vector_env``, which also holds ``forged_rejected`` equal at every tick): with
authentication every forgery is rejected and counted and the run is unchanged; without it
the forged states reach R^i past the channel (no loss, no latency) and the run is the
forged one, the same in both worlds."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from test_vector_env import _compare

from openconvoy.comms.loss import LossConfig
from openconvoy.envs import VectorConvoyEnv
from openconvoy.envs.vector.forge import first_tick
from openconvoy.policies.spec import load_policy


def test_authenticated_members_reject_and_count_every_forgery() -> None:
    forged = _compare("paper", B=2, per=0.3, faults=["forge:0@5"], steps=300)
    clean = _compare("paper", B=2, per=0.3, steps=300)
    assert forged == clean
    vec = VectorConvoyEnv(2, faults=["forge:0@5", "forge:2@10"])
    assert vec._fused is not None  # nothing but counters changes: the fused path
    vec.reset(seed=0)
    for _ in range(300):  # t = 15 s: ticks 100..300 of the first, 200..300 of the second
        vec.step(np.ones((2, 2, 2), np.float32))
    assert vec.forged_rejected.tolist() == [[101, 201 + 101, 201]] * 2
    # An autoreset starts the count again, as ConvoyEnv.reset() does.
    vec = VectorConvoyEnv(1, faults=["forge:0@0"], max_time_s=1.0)
    vec.reset(seed=0)
    for _ in range(25):  # 20 ticks, the reset, 5 more
        vec.step(np.ones((1, 2, 2), np.float32))
    assert vec.forged_rejected.tolist() == [[0, 6, 6]]


def test_without_authentication_the_forged_leader_is_chased_alike() -> None:
    modes = _compare("paper", B=2, per=0.2, faults=["forge:0@5"], auth=False)
    assert modes["failsafe"] > 0  # the followers chased it into the emergency stop


@pytest.mark.parametrize("latency_s,jitter_s", [(0.1, 0.0), (0.05, 0.15)])
def test_forgeries_overtake_late_genuine_messages(latency_s: float, jitter_s: float) -> None:
    """With latency the genuine message of a tick arrives after that tick's forgery,
    which is newer: R^i keeps the forgery and drops the late genuine one."""
    _compare("paper", B=2, per=0.2, latency_s=latency_s, jitter_s=jitter_s,
             faults=["forge:0@3"], auth=False, n_followers=3, steps=250)  # fmt: skip


@pytest.mark.parametrize("topology", ["lookahead:2", "leader-predecessor", "bidirectional"])
def test_several_forgers_and_topologies(topology: str) -> None:
    faults = ["forge:1@2", "forge:0@4", "forge:1@6", "dead:3@7"]
    _compare("paper", B=1, per=0.3, faults=faults, auth=False, n_followers=4,
             member={"topology": topology}, steps=200)  # fmt: skip


def test_forgery_on_the_track_and_in_emergency_braking() -> None:
    """On the track with GPS noise: the forger copies the claimed vehicle's true state,
    not its noisy fix. (2,500 ticks: with the braking rule of issue 22 both followers stop
    by 74 s and vehicle 1's trail alternates between its true and its forged fix 1 km
    apart every tick; by tick 2558 the trail is 5e5 m long and the twins' arc lengths,
    summed with ``math.hypot`` and ``sqrt`` (an ulp apart), pick different segments.)"""
    _compare("track", B=1, per=0.2, faults=["forge:1@4"], auth=False, gps_noise_m=0.3,
             steps=2500)  # fmt: skip
    _compare("emergency-braking", B=1, per=0.2, faults=["forge:0@3"], auth=False)


def test_a_delivered_forgery_steps_stage_by_stage_and_resets_with_the_convoy() -> None:
    vec = VectorConvoyEnv(2, faults=["forge:0@0"], auth=False, max_time_s=1.0,
                          loss=LossConfig(per=0.5))  # fmt: skip
    assert vec._fused is None
    obs, _ = vec.reset(seed=4)
    policy = load_policy("paper")
    for _ in range(vec.max_steps + 3):  # through an autoreset
        obs, *_ = vec.step(policy.act_batch(obs))
    assert (vec.forged_rejected == 0).all()
    # The leader heard at once, 1 km ahead: follower 1's leader slot (x ahead, m).
    assert obs[:, 0, 0].min() > 900.0


def test_first_tick_is_the_fault_clock() -> None:
    assert [first_tick(t, 0.05) for t in (0.0, 0.05, 5.0, 5.01, 0.3)] == [0, 1, 100, 101, 6]
    for t_s in np.linspace(0.0, 7.0, 141):
        k = first_tick(float(t_s), 0.05)
        assert k * 0.05 >= t_s - 1e-9 and not (k > 0 and (k - 1) * 0.05 >= t_s - 1e-9)
