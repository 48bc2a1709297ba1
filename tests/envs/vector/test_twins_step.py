"""The batched tick's orchestration twins against the scalar path (issue 21).

``fused_step`` and the stages it calls in compiled code (the member's ``decide`` and its
event record, the leaders' ``_drive``, the observation kernels) restate ``ConvoyEnv.step``
through ``core.tick.decide``, ``PathScenario.leader_command`` and
``ConvoyMember.observation``. Each is held here against that scalar code on random states:
the kernels called by name on a ``VectorConvoyEnv``'s arrays, the reference ``ConvoyEnv``
on its Python world (what vehicles run), both fed the same actions.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter

import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from openconvoy.comms.loss import LossConfig
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.spacing import GapChain, SpacingConfig, SpacingPolicy
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
from openconvoy.envs.scenarios import make_scenario
from openconvoy.envs.vector import leader as vleader
from openconvoy.envs.vector import member as vmember
from openconvoy.envs.vector import observation as vobservation
from openconvoy.envs.vector import plant as vplant
from openconvoy.envs.vector import step as vstep
from openconvoy.envs.vector.env import MODES
from openconvoy.envs.vector.measures import info_arrays
from openconvoy.envs.vector.plant import HEADING, ROWS, SPEED, X, Y
from openconvoy.policies.spec import load_policy

heading = st.floats(-math.pi, math.pi)


@settings(max_examples=100, deadline=None)
@given(st.lists(heading | st.floats(-50.0, 50.0), min_size=1, max_size=6))
def test_cos_sin_and_trig_rows_are_the_observations_libm(headings: list[float]) -> None:
    """``_trig_rows`` lays, and ``cos_sin`` reads, each heading's cosine and sine as
    ``ConvoyMember.observation`` computes them (``math.cos``, ``math.sin``): exactly, from
    the laid rows of a plant state and from libm on a six-row copy (the GPS-noised state)."""
    n = len(headings)
    flat = np.zeros((ROWS, n))
    flat[HEADING] = headings
    vplant._trig_rows(flat, np.arange(n, dtype=np.int64))
    own = flat.reshape(ROWS, 1, n)
    sensed = np.ascontiguousarray(own[:6])
    for i, h in enumerate(headings):
        want = (math.cos(h), math.sin(h))
        assert vplant.cos_sin(own, 0, i) == want
        assert vplant.cos_sin(sensed, 0, i) == want


@settings(max_examples=60, deadline=None)
@given(
    st.sampled_from(["paper", "track", "emergency-braking"]),
    st.floats(0.0, 1.0),
    st.floats(-3.0, 3.0),
    st.floats(-3.0, 3.0),
    heading,
    st.floats(-1.0, 6.0),
    st.floats(0.0, 80.0),
    st.none() | st.floats(0.0, 0.2),
    st.floats(0.0, 4.0),
)
@example("paper", 1.0, 0.0, 0.0, 0.0, 1.0, 30.0, 0.05, 2.0)  # the end of the open road
def test_drive_is_the_scenarios_leader_command(
    spec: str,
    frac: float,
    dx: float,
    dy: float,
    h: float,
    v: float,
    t: float,
    since: float | None,
    cmd: float,
) -> None:
    """``_project`` then ``_drive`` (the speed ramp to the profile, the stop at the end of an
    open road, pure pursuit one look-ahead ahead) against ``PathScenario.leader_command``
    from the same arc length, ramped command and last command time: the same speed
    setpoint, arc length and heading change (``ConvoyWorld``'s wrap of the absolute
    heading), to the bit (the same arithmetic, the profiles compiled from ``scenarios``)."""
    sc = make_scenario(spec, 2)
    driver = vleader.LeaderDriver(sc, 1)
    path = sc.path
    s0 = frac * path.length
    px, py = path.point_at(s0)
    x, y = px + dx, py + dy
    driver.s[0], driver.cmd[0] = s0, cmd
    driver.t_last[0] = math.nan if since is None else t - since
    sc._s, sc._cmd_speed = s0, cmd
    sc._t_last = None if since is None else t - since
    own = np.zeros((ROWS, 1, 1))
    own[X, 0, 0], own[Y, 0, 0], own[HEADING, 0, 0], own[SPEED, 0, 0] = x, y, h, v
    cmd_v, cmd_dh = np.zeros((1, 1)), np.zeros((1, 1))
    times = np.array([t])
    vleader._project(own, driver.road)
    if driver.kind == 0:  # a profile the kernel does not compile: called as the env does
        driver.target[:] = driver.profile(times, driver.s)
    vleader._drive(times, own, driver.road, cmd_v, cmd_dh)
    want_v, want_h = sc.leader_command(t, x, y, h, v)
    assert driver.s[0] == sc._s
    assert cmd_v[0, 0] == want_v and driver.cmd[0] == sc._cmd_speed
    assert cmd_dh[0, 0] == (want_h - h + math.pi) % (2 * math.pi) - math.pi
    assert driver.t_last[0] == sc._t_last


def _lockstep(
    n_followers: int,
    per: float,
    steps: int,
    seed: int,
    rush: int,
    nan_tick: int,
    spec: str,
    max_time_s: float | None = None,
    ladder: bool = False,
) -> tuple[list, Counter]:
    """``fused_step`` on a one-convoy ``VectorConvoyEnv`` and ``ConvoyEnv.step`` on the
    Python world, the same seed and actions (the ``paper`` policy on the batched
    observation, plus noise; follower ``rush`` at full speed; a NaN action of the
    last follower at ``nan_tick``) for ``steps`` ticks, in episodes of ``max_time_s``,
    the staleness ladder on where ``ladder``; asserts they agree at every tick and
    returns the safety events and the modes seen."""
    mc = load_policy("paper").member_config
    mc = dataclasses.replace(mc, ladder=LadderConfig(enabled=ladder))
    loss = LossConfig(per=per)
    vec = VectorConvoyEnv(
        1, spec, n_followers=n_followers, member_config=mc, loss=[loss], autoreset=False,
        link_counters="all", max_time_s=max_time_s,
    )  # fmt: skip
    env = ConvoyEnv(
        spec, n_followers=n_followers, member_config=mc, loss=loss, max_time_s=max_time_s,
        backend="python",
    )  # fmt: skip
    assert vec._fused is not None  # the configuration fused_step covers
    agents = env.possible_agents
    policies = [load_policy("paper") for _ in agents]
    vobs, _ = vec.reset(seed=seed)
    obs = env.reset(seed=seed)[0]
    lay = vec.layout
    parts = {  # the observation's parts by the kernel that writes them
        "_slots": slice(0, lay.own_offset),
        "observe": slice(lay.own_offset, lay.derived_offset),
        "_targets/_desired": slice(lay.derived_offset, lay.path_offset),
        "_path": slice(lay.path_offset, lay.size),
    }
    noise = np.random.default_rng(seed)
    F = n_followers
    modes: Counter = Counter()
    for k in range(steps):
        a = np.zeros((1, F, 2), np.float32)
        for j, ag in enumerate(agents):
            for part, cut in parts.items():
                np.testing.assert_allclose(
                    vobs[0, j, cut], obs[ag][cut], rtol=0, atol=1e-5, err_msg=f"{part} tick {k}"
                )
            a[0, j] = policies[j].act(vobs[0, j]) + noise.normal(0.0, 0.3, 2)
        if rush:
            a[0, rush - 1, 0] = 5.0
        if k == nan_tick:
            a[0, -1, 0] = np.nan
        vobs = np.empty((1, F, lay.size), np.float32)
        rewards, term, trunc = np.empty((1, F)), np.empty(1, bool), np.empty(1, bool)
        rows, t, own, src, meas = vec._fused.observation
        hints = src.hint.copy(), src.hint_k.copy()  # the projections' starts this tick
        vstep.fused_step(a, vobs, rewards, term, trunc, info_arrays(1, F), vec._fused)
        # observe by name on the state the tick left, from the same hints, into copies
        again = np.empty_like(vobs)
        src2 = src._replace(hint=hints[0], hint_k=hints[1], tail=src.tail.copy())
        meas2 = type(meas)(*(m.copy() for m in meas))
        vobservation.observe(again, rows, t, own, src2, meas2)
        assert np.array_equal(again, vobs)
        assert np.array_equal(src2.hint, src.hint, equal_nan=True)
        assert np.array_equal(meas2.spacing_error, meas.spacing_error, equal_nan=True)
        vec._widen_trails()
        obs, rew, env_term, env_trunc, info = env.step({ag: a[0, j] for j, ag in enumerate(agents)})
        assert np.abs(env.plant.x - vec.plant.x).max() <= 1e-9, k
        assert np.abs(env.plant.y - vec.plant.y).max() <= 1e-9, k
        assert env.safety_events == vec.safety_events(0), k  # decide's and _record's
        for j, ag in enumerate(agents):
            for part, cut in parts.items():
                np.testing.assert_allclose(
                    again[0, j, cut], obs[ag][cut], rtol=0, atol=1e-5, err_msg=f"{part} tick {k}"
                )
            i = info[ag]
            assert i["mode"] == MODES[vec.modes[0, j + 1]], (k, ag)
            modes[i["mode"]] += 1
            assert i["policy_errors"] == vec.policy_errors[0, j + 1], (k, ag)
            assert rew[ag] == pytest.approx(rewards[0, j], abs=1e-9), (k, ag)
            assert i["desired_gap_m"] == pytest.approx(vec.desired_gap[0, j + 1], abs=1e-9)
        assert env_term[agents[0]] == bool(term[0]) and env_trunc[agents[0]] == bool(trunc[0])
        if not env.agents:
            break
    return env.safety_events, modes


@settings(max_examples=30, deadline=None)
@given(
    st.integers(1, 3),
    st.floats(0.0, 0.95),
    st.integers(2, 100),
    st.integers(0, 2**16),
    st.integers(0, 3),
    st.integers(-1, 100),
    st.sampled_from(["paper", "emergency-braking"]),
    st.none() | st.sampled_from([0.5, 1.0, 2.5]),
    st.booleans(),
)
def test_fused_step_and_its_stages_are_convoy_env_step(
    n_followers: int,
    per: float,
    steps: int,
    seed: int,
    rush: int,
    nan_tick: int,
    spec: str,
    max_time_s: float | None,
    ladder: bool,
) -> None:
    """``fused_step`` (``decide``, ``_drive``, the plant, the clock, the channel,
    ``observe`` with ``_slots``, ``_targets``, ``_desired``, ``_path`` and the prefetch
    ``_warm``, the measures, terminations) against ``ConvoyEnv.step`` on random runs:
    observations within float32 rounding part by part, the plant within 1e-9 m, modes,
    policy errors and safety events identical, rewards and desired gaps within 1e-9 (the
    kernels' ``norm`` is ``hypot`` within an ulp); episodes truncated alike; the staleness
    ladder on or off."""
    _lockstep(
        n_followers, per, steps, seed, min(rush, n_followers), nan_tick, spec, max_time_s, ladder
    )


def test_fused_step_records_the_emergency_stop_and_policy_error_as_convoy_env() -> None:
    """The rare branches (``decide``'s latches, ``_record``): a follower rushing into its
    predecessor latches the emergency stop (ConvoyEnv's event at 4.15 s), a NaN action
    is a policy error; both worlds record the same events."""
    events, _ = _lockstep(2, 0.1, 90, 3, 1, 10, "paper")
    kinds = [text.split(":")[0] for _, _, text in events]
    assert "emergency stop" in kinds and len(events) >= 2, events


def test_fused_step_takes_the_ladders_rungs_as_convoy_env() -> None:
    """``decide``'s ladder (``_rung``, ``_ladder``) under heavy loss: both worlds degrade
    and stop alike."""
    _, modes = _lockstep(2, 0.9, 100, 5, 0, -1, "paper", ladder=True)
    assert modes["degraded"] > 0 and modes["stop"] > 0, modes


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from(["constant-distance", "constant-time-headway", "quadratic"]),
    st.lists(st.floats(0.2, 6.0), min_size=2, max_size=6),
    st.floats(-2.0, 40.0),
    st.data(),
)
def test_desired_is_the_gap_chain(
    kind: str, lengths: list[float], speed: float, data: st.DataObject
) -> None:
    """``_desired`` (the desired arc gap of follower ``f + 1`` to its target ``m``: 0 the
    leader, m its m-th predecessor) against ``GapChain.gap_to``, what ``ConvoyMember``
    sums: to the bit (the same pair gaps added in the same order; under constant
    distance the leader's the sum ``observe`` carries from follower to follower)."""
    F = len(lengths) - 1
    f = data.draw(st.integers(0, F - 1))
    m = data.draw(st.integers(0, f + 1))
    config = SpacingConfig(kind=kind, distance_m=12.5, standstill_m=2.0, headway_s=0.8)
    chain = GapChain(SpacingPolicy(config), lengths)
    sp = vmember.pack_spacing(config)
    lead = 0.0
    for _ in range(f + 1):
        lead += sp[1]
    got = vobservation._desired(f, m, speed, sp, np.array(lengths), F, lead)
    assert got == chain.gap_to(f + 1, 0 if m == 0 else f + 1 - m, speed)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=6, max_size=6), st.integers(1, 4))
def test_record_keeps_what_the_worlds_stop_event_reads(read: list[float], i: int) -> None:
    """``_record`` (vehicle ``i``'s emergency stop) keeps the six numbers
    ``ConvoyWorld._rule_fires`` reads, in ``EVENT_ROWS``' order and counted once, so the
    event text made of them (the rule's ``reason``, ``VectorEvents``) is the world's."""
    B, N = 2, 5
    nan = np.full((len(vmember.EVENT_ROWS), B, N), np.nan)
    out = vmember.Commands(
        np.zeros((B, N), np.int64), np.zeros((B, N), bool), np.zeros((B, N), bool),
        np.zeros((B, N)), np.zeros((B, N)), np.zeros((B, N), np.int64), nan,
        np.zeros(B, np.int64),
    )  # fmt: skip
    vmember._record(out, 1, i, tuple(read))
    rows = dict(zip(vmember.EVENT_ROWS, out.events[:, 1, i]))
    t, bumper, closing, ego, decel, accel = read
    assert rows["estop_t_s"] == t and out.n_events.tolist() == [0, 1]
    kept = [rows[k] for k in ("estop_bumper_m", "estop_closing_mps", "estop_ego_mps",
                              "estop_pred_decel", "estop_ego_accel")]  # fmt: skip
    assert kept == [bumper, closing, ego, decel, accel]
    # nothing else written: the other convoy, the other vehicles, the policy-error rows
    assert np.isnan(out.events[:, 0]).all() and np.isnan(out.events[:3, 1, i]).all()
    assert np.isnan(np.delete(out.events[:, 1], i, axis=1)).all()
