"""VectorConvoyEnv against ConvoyEnv: the same seeds and actions give the same runs.

Each case runs B convoys in one ``VectorConvoyEnv`` and B ``ConvoyEnv``s side by side, the
``paper`` policy acting on the batched observations and both worlds taking those actions.
Deliveries, counters, modes, rewards, terminations and safety events must be identical,
plant states within 1e-9 m, observations within float32 rounding.
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.comms.loss import LossConfig, counter_uniform, counter_uniform_array
from openconvoy.core.controllers import HeadingControlConfig, SpeedControlConfig
from openconvoy.core.errors import ConfigError
from openconvoy.core.gates import TriggerConfig
from openconvoy.core.ladder import LadderConfig
from openconvoy.core.spacing import SpacingConfig
from openconvoy.envs import ConvoyEnv, VectorConvoyEnv
from openconvoy.envs.gps import gps_noise, vehicle_states
from openconvoy.envs.vector.env import MODES
from openconvoy.policies.classical import ClassicalPolicy
from openconvoy.policies.spec import load_policy
from tests.python_world import python_world  # noqa: F401 - reads the Python world


def _compare(
    scenario: str = "paper",
    B: int = 2,
    per: float | list[float] = 0.3,
    latency_s: float = 0.0,
    jitter_s: float = 0.0,
    samples_s: tuple[float, ...] = (),
    stamp: tuple[float, float] = (0.0, 0.0),
    links: tuple[tuple[float, ...], ...] = (),
    staleness: tuple[float, ...] = (),
    steps: int | None = None,
    n_followers: int | None = None,
    member: dict | None = None,
    model: str = "bernoulli",
    corrupt=None,
    events_out: list | None = None,
    **kwargs,
) -> Counter:
    """Run both worlds; assert they agree at every tick; return the modes seen (and
    append each convoy's last safety events to ``events_out``)."""
    mc = load_policy("paper").member_config
    if member:
        mc = dataclasses.replace(mc, **member)
    pers = per if isinstance(per, list) else [per] * B
    losses = [
        LossConfig(
            per=p,
            latency_s=latency_s,
            jitter_s=jitter_s,
            latency_samples_s=samples_s,
            stamp_error_s=stamp[0],
            stamp_drift=stamp[1],
            link_latency_s=links,
            staleness_s=staleness,
            model=model,
            mean_burst_s=0.4,
        )
        for p in pers
    ]
    vec = VectorConvoyEnv(
        B,
        scenario,
        n_followers=n_followers,
        member_config=mc,
        loss=losses,
        autoreset=False,
        link_counters="all",  # ConvoyEnv's counters
        **kwargs,
    )
    envs = [
        ConvoyEnv(scenario, n_followers=n_followers, member_config=mc, loss=c, **kwargs)
        for c in losses
    ]
    agents = envs[0].possible_agents
    policies = [[load_policy("paper") for _ in agents] for _ in envs]
    obs = [e.reset(seed=10 + b)[0] for b, e in enumerate(envs)]
    vobs, _ = vec.reset(seed=10)
    modes: Counter = Counter()
    N = vec.n_vehicles
    for k in range(steps or envs[0].max_steps):
        actions = np.zeros((B, N - 1, 2), np.float32)
        for b in range(B):
            for j, a in enumerate(agents):
                np.testing.assert_allclose(
                    vobs[b, j], obs[b][a], rtol=0, atol=1e-5, err_msg=f"tick {k}"
                )
                actions[b, j] = policies[b][j].act(vobs[b, j])
        if corrupt is not None:
            actions = corrupt(k, actions)
        vobs, vrew, vterm, vtrunc, vinfo = vec.step(actions)
        for b, env in enumerate(envs):
            obs[b], rew, term, trunc, info = env.step(
                {a: actions[b, j] for j, a in enumerate(agents)}
            )
            x, y = vec.plant.x.reshape(B, N)[b], vec.plant.y.reshape(B, N)[b]
            assert np.abs(env.plant.x - x).max() <= 1e-9 and np.abs(env.plant.y - y).max() <= 1e-9
            for j, a in enumerate(agents):
                i = info[a]
                assert i["mode"] == MODES[vinfo["mode"][b, j]], (k, b, a)
                modes[i["mode"]] += 1
                for key in (
                    "msgs_sent",
                    "msgs_received",
                    "msgs_kept",
                    "msgs_lost",
                    "policy_errors",
                ):
                    assert i[key] == vinfo[key][b, j], (k, b, a, key)
                assert rew[a] == pytest.approx(vrew[b, j], abs=1e-9)
                for key in ("gap_m", "speed_mps"):
                    assert i[key] == pytest.approx(vinfo[key][b, j], abs=1e-9)
            assert term[agents[0]] == bool(vterm[b]) and trunc[agents[0]] == bool(vtrunc[b]), k
            assert env.forged_rejected == vec.forged_rejected[b].tolist(), k
            assert env.safety_events == vec.safety_events(b), k
        if not envs[0].agents:
            break
    if events_out is not None:
        events_out.extend(vec.safety_events(b) for b in range(B))
    return modes


def test_counter_draws_are_the_same_scalar_and_batched() -> None:
    key = 2**62 + 12345
    s, r, n = np.meshgrid(range(4), range(4), range(50), indexing="ij")
    batched = counter_uniform_array(np.uint64(key), s, r, n, 0)
    scalar = [counter_uniform(key, a, b, c, 0) for a, b, c in zip(s.ravel(), r.ravel(), n.ravel())]
    assert batched.ravel().tolist() == scalar
    assert 0.0 <= batched.min() and batched.max() < 1.0
    assert abs(batched.mean() - 0.5) < 0.05


def test_paper_scenario_whole_episode_under_loss() -> None:
    modes = _compare("paper", B=1, per=0.3)
    # ``stop`` only while a follower has not yet heard its predecessor (the braking rule's
    # BLIND, core.safety.verdict): the first messages lost, at the start.
    assert set(modes) == {"coop", "stop"}
    assert modes["stop"] == 4  # of 2400 follower ticks


@pytest.mark.parametrize(
    "topology",
    [
        "predecessor",
        "all-predecessors",
        "lookahead:2",
        "leader",
        "leader-predecessor",
        "bidirectional",
        "all",
    ],
)
def test_every_topology(topology: str) -> None:
    _compare("paper", B=1, per=0.3, n_followers=4, member={"topology": topology}, steps=80)


@pytest.mark.parametrize("scenario,steps", [("track", 300), ("emergency-braking", None)])
def test_track_and_emergency_braking(scenario: str, steps: int | None) -> None:
    _compare(scenario, B=1, per=0.2, steps=steps)


def test_event_trigger() -> None:
    _compare("paper", B=1, per=0.2, member={"trigger": TriggerConfig(kind="event")}, steps=250)


def test_latency_and_per_convoy_seeds() -> None:
    _compare("paper", B=3, per=0.2, latency_s=0.12, steps=120)


def test_latency_jitter_reorders_messages_as_convoy_env() -> None:
    # Jitter 0.2 s > the 0.1 s send period: later broadcasts overtake earlier ones.
    modes = _compare("paper", B=2, per=0.2, latency_s=0.05, jitter_s=0.2, n_followers=3, steps=200)
    assert modes["coop"] > 0


def test_jitter_without_base_latency_and_with_bursts() -> None:
    _compare("paper", B=1, per=0.3, jitter_s=0.08, steps=150)
    _compare(
        "paper", B=2, per=0.4, model="gilbert-elliott", latency_s=0.1, jitter_s=0.15, steps=150
    )


def test_latency_samples_and_sub_tick_delays_as_convoy_env() -> None:
    """Delays drawn from measured message ages (0.007-0.11 s, not whole 0.05 s ticks):
    both worlds draw the same delays and advance each message by its wait for the tick."""
    modes = _compare("paper", B=2, per=0.1, samples_s=(0.007, 0.034, 0.048, 0.11), steps=200)
    assert modes["coop"] > 0


def test_senders_clock_error_as_convoy_env() -> None:
    """Messages stamped 0.157 s + 4 ms/s early (sitl/convoy vx-fixed-per0.3), with and
    without a delay: the same stamps, the same dead reckoning in both worlds."""
    _compare("paper", B=1, per=0.0, stamp=(0.157, 0.004), steps=120)
    _compare("paper", B=1, per=0.2, samples_s=(0.01, 0.05), stamp=(0.05, 0.0), steps=120)


def test_senders_staleness_as_convoy_env() -> None:
    """Each sender's messages stamped older by its telemetry staleness (vx-fixed-2's 36 /
    33 / 10 ms) on top of the link delays (7 ms): the same stamps in both worlds."""
    links = ((0, 1, 0.0043, 0.0072, 0.064), (1, 2, 0.0065), (0, 2, 0.014))
    _compare("paper", B=2, per=0.1, links=links, staleness=(0.036, 0.033, 0.01), steps=150)
    _compare("paper", B=1, per=0.0, staleness=(0.036, 0.0, 0.01), stamp=(0.05, 0.001), steps=80)


def test_per_link_delays_as_convoy_env() -> None:
    """Each link its own delay distribution (vx-fixed-1's 34 / 53 / 27 ms), the rest the
    common one (none here: instant)."""
    links = ((0, 1, 0.032, 0.034, 0.045), (1, 2, 0.051, 0.053, 0.063), (0, 2, 0.027))
    _compare("paper", B=2, per=0.1, links=links, steps=150)


def test_jittered_channel_is_staged_not_fused() -> None:
    vec = VectorConvoyEnv(1, loss=LossConfig(per=0.1, jitter_s=0.05))
    assert vec._fused is None and vec.channel.slots == 1 + 3
    assert VectorConvoyEnv(1, loss=LossConfig(per=0.1))._fused is not None


def test_gps_noise_draws_are_the_same_in_both_envs() -> None:
    modes = _compare("paper", B=2, per=0.2, gps_noise_m=0.3, n_followers=3, steps=200)
    assert modes["coop"] > 0


@pytest.mark.parametrize("trigger", ["periodic", "event"])
def test_gps_noise_with_latency_jitter_and_track(trigger: str) -> None:
    member = {"trigger": TriggerConfig(kind=trigger)}
    _compare("track", B=2, per=0.2, latency_s=0.05, jitter_s=0.1, gps_noise_m=0.2,
             member=member, steps=150)  # fmt: skip


def test_gps_noise_is_standard_normal_and_moves_only_what_members_see() -> None:
    states = vehicle_states(2**62 + 7, 50)
    z = np.array([gps_noise(states, 1.0, k) for k in range(400)])  # (ticks, axis, vehicle)
    assert abs(z.mean()) < 0.02 and abs(z.std() - 1.0) < 0.02
    assert abs(np.corrcoef(z[:, 0].ravel(), z[:, 1].ravel())[0, 1]) < 0.03
    vec = VectorConvoyEnv(2, gps_noise_m=0.5)
    vec.reset(seed=3)
    truth = np.array(vec.own_truth)
    off = vec._sensed[:2] - truth[:2]
    assert 0.0 < np.abs(off).max() < 5 * 0.5 and (vec._sensed[2:] == truth[2:]).all()
    assert vec._fused is None and VectorConvoyEnv(2)._fused is not None


def test_gilbert_elliott_bursts() -> None:
    _compare("paper", B=2, per=0.4, model="gilbert-elliott", n_followers=3, steps=200)


@pytest.mark.parametrize("model", ["bernoulli", "gilbert-elliott"])
def test_one_per_per_convoy_for_batched_sweeps(model: str) -> None:
    _compare("paper", B=3, per=[0.0, 0.3, 0.6], model=model, steps=150)


@pytest.mark.parametrize("kind", ["constant-time-headway", "quadratic"])
def test_spacing_policies(kind: str) -> None:
    _compare(
        "paper",
        B=1,
        per=0.2,
        n_followers=3,
        member={"spacing": SpacingConfig(kind=kind)},
        steps=150,
    )


def test_staleness_ladder_under_heavy_loss() -> None:
    modes = _compare(
        "paper", B=1, per=0.9, member={"ladder": LadderConfig(enabled=True)}, steps=300
    )
    assert modes["degraded"] > 0 and modes["stop"] > 0  # the ladder's rungs were exercised


def test_faults_and_emergency_stop() -> None:
    modes = _compare("paper", B=1, per=0.1, faults=["dead:1@5", "silent:0@8"], steps=260)
    assert modes["stop"] > 0


def test_a_non_finite_action_stops_the_follower_as_in_convoy_env() -> None:
    """The one-tick rule in the batched world too: NaN is a counted policy error and a
    latched stop (failsafe), never a command to the plant."""

    def corrupt(k: int, actions: np.ndarray) -> np.ndarray:
        if k in (200, 201):
            actions = actions.copy()
            actions[0, 0, 0] = np.nan
        return actions

    modes = _compare(steps=300, corrupt=corrupt)
    assert modes["failsafe"] == 100  # follower 1 of convoy 0, from tick 200 to the end


def test_autoreset_starts_the_next_episode_in_the_same_step() -> None:
    vec = VectorConvoyEnv(3, "paper", max_time_s=1.0)
    obs, _ = vec.reset(seed=3)
    first = obs.copy()
    actions = np.tile(np.array([1.0, 0.0], np.float32), (3, 2, 1))
    for _ in range(vec.max_steps):
        obs, _, term, trunc, info = vec.step(actions)
    assert trunc.all() and not term.any()
    assert "final_observation" in info
    assert (vec.step_count == 0).all() and (vec.t == 0.0).all()
    # The new episode starts where the first one did (same scenario start, fresh buffers
    # apart from the seed-dependent loss draws, which are off here).
    np.testing.assert_array_equal(obs, first)


def test_unsupported_options_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="gps_noise_m"):
        VectorConvoyEnv(2, gps_noise_m=-0.5)
    with pytest.raises(ConfigError, match="path scenarios"):
        VectorConvoyEnv(2, "highway-cut-in")
    with pytest.raises(ConfigError, match="render"):
        VectorConvoyEnv(2, render_mode="rgb_array")
    with pytest.raises(ConfigError, match="link_counters must be 'kept' or 'all'"):
        VectorConvoyEnv(2, link_counters="some")
    with pytest.raises(ConfigError, match="num_envs"):
        VectorConvoyEnv(0)


def _pid_pure_pursuit() -> ClassicalPolicy:
    base = load_policy("paper").config
    return ClassicalPolicy(
        dataclasses.replace(
            base,
            speed=SpeedControlConfig(kind="pid", ki=0.2),
            heading=HeadingControlConfig(kind="pure-pursuit"),
        )
    )


@pytest.mark.parametrize(
    "make,per",
    [
        (lambda: load_policy("paper"), 0.3),
        (lambda: load_policy("paper"), 0.8),
        (lambda: load_policy("mcacc"), 0.3),
        (_pid_pure_pursuit, 0.5),
    ],
)
def test_batched_policy_matches_one_policy_per_vehicle(make, per: float) -> None:
    B = 3
    probe = make()
    ladder = LadderConfig(enabled=True) if per > 0.5 else LadderConfig()
    mc = dataclasses.replace(probe.member_config, ladder=ladder)
    vec = VectorConvoyEnv(B, "paper", n_followers=3, member_config=mc, loss=LossConfig(per=per))
    batched = make()
    singles = [[make() for _ in range(3)] for _ in range(B)]
    obs, _ = vec.reset(seed=5)
    for _ in range(250):
        got = batched.act_batch(obs)
        want = np.array([[singles[b][j].act(obs[b, j]) for j in range(3)] for b in range(B)])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        obs, *_ = vec.step(got)


def test_classical_reset_rows_forgets_only_those_rows() -> None:
    """A convoy whose episode restarts gets a fresh PID integrator; the other keeps its own.
    On the track the integrator wound up before tick 200 moves the speed from tick ~820 on,
    so a reset that did nothing would fail the comparison there."""
    vec = VectorConvoyEnv(2, "track", n_followers=2, loss=LossConfig(per=0.2))
    batched = _pid_pure_pursuit()
    singles = [[_pid_pure_pursuit() for _ in range(2)] for _ in range(2)]
    obs, _ = vec.reset(seed=8)
    for t in range(900):
        if t == 200:
            batched.reset_rows(np.array([[False, False], [True, True]]))
            singles[1] = [_pid_pure_pursuit() for _ in range(2)]
        got = batched.act_batch(obs)
        want = np.array([[singles[b][j].act(obs[b, j]) for j in range(2)] for b in range(2)])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
        obs, *_ = vec.step(got)


@pytest.mark.parametrize(
    "loss",
    [
        LossConfig(per=0.4),
        LossConfig(per=0.4, latency_s=0.02, jitter_s=0.08),
        LossConfig(per=0.4, model="gilbert-elliott", mean_burst_s=0.3),
    ],
    ids=["bernoulli", "jitter", "gilbert-elliott"],
)
def test_kept_link_counters_give_the_same_run(loss: LossConfig) -> None:
    """Loss drawn on the kept links only (the default) or on every pair: the same
    deliveries into R^i, so the same run; only the counters of never-kept links differ."""
    mc = dataclasses.replace(load_policy("paper").member_config, topology="lookahead:1")
    envs = [
        VectorConvoyEnv(2, "paper", n_followers=5, member_config=mc, loss=loss, link_counters=c)
        for c in ("all", "kept")
    ]
    assert envs[1].link_counters == "kept"
    assert VectorConvoyEnv(1, "paper", loss=loss).link_counters == "kept"  # the default
    obs = [e.reset(seed=1)[0] for e in envs]
    policy = load_policy("paper")
    for _ in range(150):
        np.testing.assert_array_equal(obs[0], obs[1])
        actions = policy.act_batch(obs[0])
        out = [e.step(actions) for e in envs]
        obs = [o[0] for o in out]
        np.testing.assert_array_equal(envs[0].plant.x, envs[1].plant.x)
        for key in ("msgs_kept", "msgs_sent", "msgs_offered", "mode"):
            np.testing.assert_array_equal(out[0][4][key], out[1][4][key])
    info_all, info_kept = out[0][4], out[1][4]
    sent = np.concatenate([info_all["leader_msgs_sent"][:, None], info_all["msgs_sent"]], axis=1)
    # msgs_offered in closed form: every other vehicle's broadcasts.
    np.testing.assert_array_equal(info_all["msgs_offered"], sent.sum(1)[:, None] - sent[:, 1:])
    settled = info_all["msgs_received"] + info_all["msgs_lost"]
    if loss.latency.instant:  # every pair's draw is made at the send
        np.testing.assert_array_equal(settled, info_all["msgs_offered"])
    else:  # some still in flight
        assert (settled <= info_all["msgs_offered"]).all() and (settled > 0).all()
    # Kept links counted: lookahead:1 keeps the predecessor's only, so each follower's
    # received + lost is its predecessor's broadcasts (less those in flight).
    kept_settled = info_kept["msgs_received"] + info_kept["msgs_lost"]
    if loss.latency.instant:
        np.testing.assert_array_equal(kept_settled, sent[:, :-1])
    assert (kept_settled <= sent[:, :-1]).all() and (info_kept["msgs_lost"] > 0).all()
    assert (info_kept["msgs_received"] < info_all["msgs_received"]).all()
    np.testing.assert_array_equal(info_kept["msgs_received"], info_kept["msgs_kept"])


def test_gymnasium_vector_api() -> None:
    from gymnasium.vector import AutoresetMode

    from openconvoy.envs.vector.adapters import ConvoyVectorEnv

    venv = ConvoyVectorEnv(VectorConvoyEnv(3, "paper", max_time_s=0.25))
    assert venv.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    obs, infos = venv.reset(seed=4)
    assert venv.num_envs == 6 and obs.shape == venv.observation_space.shape
    assert venv.observation_space.contains(obs)
    first = obs.copy()
    for k in range(5):
        obs, rew, term, trunc, infos = venv.step(venv.action_space.sample())
        assert rew.shape == term.shape == trunc.shape == (6,)
        assert (k == 4) == ("final_obs" in infos)
    assert trunc.all() and infos["_final_obs"].all()
    assert not np.array_equal(infos["final_obs"], obs)
    np.testing.assert_array_equal(obs, first)  # same-step autoreset: the new episode's first


def test_autoreset_continues_each_convoys_seed_like_convoy_env_reset() -> None:
    """Episode 2 after an autoreset is ConvoyEnv's ``reset()`` (no seed) after episode 1."""
    B, loss = 2, LossConfig(per=0.5)
    mc = load_policy("paper").member_config
    vec = VectorConvoyEnv(
        B, "paper", member_config=mc, loss=loss, max_time_s=1.0, link_counters="all"
    )
    envs = [ConvoyEnv("paper", member_config=mc, loss=loss, max_time_s=1.0) for _ in range(B)]
    vobs, _ = vec.reset(seed=7)
    obs = [e.reset(seed=7 + b)[0] for b, e in enumerate(envs)]
    actions = np.tile(np.array([1.2, 0.01], np.float32), (B, 2, 1))
    for _episode in range(2):
        for _ in range(vec.max_steps):
            vobs, _, _, vtrunc, vinfo = vec.step(actions)
            for b, e in enumerate(envs):
                obs[b], _, _, trunc, info = e.step(
                    {a: actions[b, j] for j, a in enumerate(e.possible_agents)}
                )
                assert [info[a]["msgs_lost"] for a in e.possible_agents] == vinfo["msgs_lost"][
                    b
                ].tolist()
        assert vtrunc.all()
        obs = [e.reset()[0] for e in envs]
        for b, e in enumerate(envs):
            np.testing.assert_array_equal(np.stack([obs[b][a] for a in e.possible_agents]), vobs[b])
