"""Learned-policy loading without the training stack: the .npz artifact, its numpy forward
pass, residual composition, layout checks and running with torch absent."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from openconvoy.core.member import ConvoyMember, MemberConfig
from openconvoy.core.observation import ObservationLayout
from openconvoy.core.state import VehicleState
from openconvoy.policies import load_policy
from openconvoy.policies.learned import (
    LearnedMeta,
    NumpyMLP,
    compose_action,
    load_learned,
    save_npz,
)
from openconvoy.policies.presets import PRESETS

ROOT = Path(__file__).resolve().parents[2]


def _meta(member: MemberConfig | None = None, base=None, **kw) -> LearnedMeta:
    member = member or PRESETS["paper"].member
    size = member.layout.size
    rng = np.random.default_rng(1)
    return LearnedMeta(
        algo="ppo",
        layout=member.layout.describe(),
        member_config=member,
        control_rate_hz=20.0,
        action_low=(0.0, -0.5),
        action_high=(5.0, 0.5),
        obs_mean=rng.normal(size=size),
        obs_var=rng.uniform(0.5, 2.0, size=size),
        obs_clip=10.0,
        base=base,
        residual_scale=(0.5, 0.1) if base is not None else (0.0, 0.0),
        **kw,
    )


def _mlp(size: int, output: str = "clip", activation: str = "tanh", seed: int = 0) -> NumpyMLP:
    rng = np.random.default_rng(seed)
    shapes = [(16, size), (16, 16), (2, 16)]
    return NumpyMLP(
        [rng.normal(scale=0.3, size=s) for s in shapes],
        [rng.normal(scale=0.1, size=s[0]) for s in shapes],
        activation,
        output,
    )


@pytest.fixture
def npz(tmp_path: Path) -> Path:
    meta = _meta()
    return save_npz(tmp_path / "policy.npz", meta, _mlp(meta.layout["size"]))


def _member_observation(member: MemberConfig) -> np.ndarray:
    """A real observation: follower 1 of a 3-vehicle convoy that heard the leader."""
    m = ConvoyMember(1, 3, member, [0.779, 0.97, 0.779])
    m.observe_own(VehicleState(1, 1.0, -15.3, 0.2, 1.0, 0.02, 0.1, 0.0, 0.97, 0.49))
    for t in (0.8, 0.9, 1.0):
        m.receive(VehicleState(0, t, 1.0 * t, 0.0, 1.0, 0.0, 0.0, 0.0, 0.779, 0.29), 1.0)
    return m.observation(1.0)


def test_numpy_forward_is_the_mlp_written_out() -> None:
    mlp = _mlp(5, output="tanh", activation="relu")
    x = np.linspace(-1, 1, 5)
    h = np.maximum(mlp.weights[0] @ x + mlp.biases[0], 0)
    h = np.maximum(mlp.weights[1] @ h + mlp.biases[1], 0)
    expected = np.tanh(mlp.weights[2] @ h + mlp.biases[2])
    np.testing.assert_allclose(mlp(x), expected, rtol=0, atol=1e-12)
    # A batch gives the rows' results.
    np.testing.assert_allclose(mlp(np.stack([x, -x]))[0], expected, atol=1e-12)


def test_npz_round_trip_and_act(npz: Path) -> None:
    policy = load_learned(npz)
    meta = _meta()
    assert policy.meta.layout == meta.layout
    assert policy.member_config == PRESETS["paper"].member
    assert policy.control_rate_hz == 20.0
    np.testing.assert_array_equal(policy.meta.obs_mean, meta.obs_mean)
    obs = _member_observation(policy.member_config)
    # act = scale(mlp(normalize(obs))) with the recorded statistics.
    z = np.clip((obs - meta.obs_mean) / np.sqrt(meta.obs_var + meta.obs_epsilon), -10, 10)
    a = np.clip(_mlp(meta.layout["size"])(z), -1, 1)
    expected = np.array([0.0, -0.5]) + 0.5 * (a + 1) * np.array([5.0, 1.0])
    np.testing.assert_allclose(policy.act(obs), expected, atol=1e-6)
    assert policy.act(obs).dtype == np.float32
    # The spec grammar reaches the same loader.
    np.testing.assert_array_equal(load_policy(str(npz)).act(obs), policy.act(obs))


def test_absolute_actions_span_the_recorded_range() -> None:
    low, high = (0.0, -0.5), (5.0, 0.5)
    np.testing.assert_allclose(compose_action(np.array([-1.0, -1.0]), low, high), [0.0, -0.5])
    np.testing.assert_allclose(compose_action(np.array([1.0, 1.0]), low, high), [5.0, 0.5])
    np.testing.assert_allclose(compose_action(np.array([0.0, 0.0]), low, high), [2.5, 0.0])
    # Out-of-range network outputs are clipped, never extrapolated.
    np.testing.assert_allclose(compose_action(np.array([3.0, -7.0]), low, high), [5.0, -0.5])


def test_residual_actions_correct_the_base_within_bounds() -> None:
    low, high, scale = (0.0, -1.5), (5.0, 1.5), (0.5, 0.1)
    base = np.array([2.0, 0.2])
    np.testing.assert_allclose(
        compose_action(np.zeros(2), low, high, base, scale), [2.0, 0.2], atol=1e-7
    )
    np.testing.assert_allclose(
        compose_action(np.array([1.0, -1.0]), low, high, base, scale), [2.5, 0.1], atol=1e-7
    )
    np.testing.assert_allclose(
        compose_action(np.array([-1.0, 0.0]), low, high, np.array([0.2, 0.0]), scale), [0.0, 0.0]
    )


def test_residual_policy_with_zero_network_is_its_base(tmp_path: Path) -> None:
    base = PRESETS["paper"]
    meta = _meta(base=base)
    size = meta.layout["size"]
    zero = NumpyMLP([np.zeros((2, size))], [np.zeros(2)], "tanh", "clip")
    policy = load_learned(save_npz(tmp_path / "r.npz", meta, zero))
    assert policy.meta.base == base
    obs = _member_observation(base.member)
    classical = load_policy("paper")
    np.testing.assert_allclose(policy.act(obs), classical.act(obs), atol=1e-6)
    assert policy.act(obs)[0] > 0.5  # the base really drives (it heard a moving leader)


def test_layout_mismatch_is_refused_with_a_clear_message(npz: Path) -> None:
    other = MemberConfig(M=3, k=3)
    with pytest.raises(
        ValueError, match=r"observation layout \(M 2 vs 3, size 111 vs 137 in this convoy config\)"
    ):
        load_learned(npz, member_config=other)
    with pytest.raises(
        ValueError, match=r"policy.npz: policy was trained for another observation layout"
    ):
        load_learned(npz, layout=ObservationLayout(M=2, k=5))
    policy = load_learned(npz, layout=ObservationLayout(M=2, k=3))  # the same layout loads
    with pytest.raises(ValueError, match="k 3 vs 4"):
        policy.check_layout(ObservationLayout(M=2, k=4))
    # An observation of the wrong size is refused, not silently truncated.
    with pytest.raises(ValueError, match=r"layout expects \(111,\)"):
        policy.act(np.zeros(137, dtype=np.float32))


def test_metadata_whose_member_config_disagrees_with_its_layout_is_refused() -> None:
    member = PRESETS["paper"].member
    with pytest.raises(ValueError, match="another observation layout"):
        LearnedMeta(
            algo="ppo",
            layout={"version": 1, "M": 3, "k": 3, "size": 137},
            member_config=member,
            control_rate_hz=20.0,
            action_low=(0.0, -0.5),
            action_high=(5.0, 0.5),
        )


def test_not_a_policy_export_is_refused(tmp_path: Path) -> None:
    bad = tmp_path / "weights.npz"
    np.savez(bad, W0=np.zeros((2, 2)))
    with pytest.raises(ValueError, match="not an OpenConvoy policy export"):
        load_learned(bad)
    with pytest.raises(FileNotFoundError, match="policy file not found"):
        load_policy(str(tmp_path / "missing.npz"))


def test_zip_without_openconvoy_metadata_is_refused(tmp_path: Path) -> None:
    import zipfile

    path = tmp_path / "sb3.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("data", "{}")
    with pytest.raises(ValueError, match="without OpenConvoy metadata"):
        load_learned(path)


def test_npz_loads_and_acts_with_torch_absent(npz: Path) -> None:
    """A vehicle without the train extra: ``import torch`` fails, the .npz still drives."""
    code = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None  # any import of torch now raises ImportError
        sys.modules["stable_baselines3"] = None
        import numpy as np
        from openconvoy.policies import load_policy
        p = load_policy({str(npz)!r})
        a = p.act(np.zeros(p.layout.size, dtype=np.float32))
        assert a.shape == (2,) and np.all(np.isfinite(a))
        assert "torch" not in {{k for k, v in sys.modules.items() if v is not None}}
        print("ok", p.control_rate_hz, p.layout.describe()["size"])
    """)
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok", "20.0", "111"]


def _rollout_observations(member: MemberConfig, steps: int = 40) -> np.ndarray:
    """Observations ``(steps, B, N-1, D)`` of 3 paper convoys under loss (seeds 4, 5, 6),
    driven by the paper controller (real member output: fresh, stale and lost targets)."""
    import copy

    from openconvoy.comms.loss import LossConfig
    from openconvoy.envs import ConvoyEnv

    convoys = []
    for seed in (4, 5, 6):
        env = ConvoyEnv("paper", member_config=member, loss=LossConfig(per=0.5))
        obs, _ = env.reset(seed=seed)
        drivers = {a: copy.deepcopy(load_policy("paper")) for a in env.agents}
        frames = []
        for _ in range(steps):
            frames.append(np.stack([obs[a] for a in env.possible_agents]))
            obs, *_ = env.step({a: drivers[a].act(o) for a, o in obs.items()})
        convoys.append(frames)
    return np.array(convoys).transpose(1, 0, 2, 3)


@pytest.mark.parametrize("residual", [False, True])
def test_act_batch_equals_act_row_by_row(tmp_path: Path, residual: bool) -> None:
    """One forward pass over (B, N-1, D) gives every row's ``act``, a residual base keeping
    each row's controller state across calls as one policy per vehicle does."""
    import copy

    base = PRESETS["paper"] if residual else None
    meta = _meta(base=base)
    policy = load_learned(save_npz(tmp_path / "p.npz", meta, _mlp(meta.layout["size"])))
    frames = _rollout_observations(meta.member_config)
    rows = [[copy.deepcopy(policy) for _ in range(frames.shape[2])] for _ in range(frames.shape[1])]
    batched = copy.deepcopy(policy)
    for obs in frames:
        got = batched.act_batch(obs)
        assert got.shape == obs.shape[:-1] + (2,) and got.dtype == np.float32
        want = np.array([[p.act(o) for p, o in zip(ps, os)] for ps, os in zip(rows, obs)])
        np.testing.assert_array_equal(got, want)
    # A flat (B, D) batch and a single row work too.
    flat = frames[-1].reshape(-1, meta.layout["size"])
    assert batched.act_batch(flat).shape == (flat.shape[0], 2)
    with pytest.raises(ValueError, match="layout expects"):
        batched.act_batch(flat[:, :-1])
