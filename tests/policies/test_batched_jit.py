"""The compiled ``act_batch`` (``policies.batched_jit``) is ``ClassicalPolicy.act`` to the bit.

Whole episodes of ``VectorConvoyEnv`` under loss, driven by the per-row ``act``: at every
tick the compiled batch, the numpy fallback and one ``ClassicalPolicy`` per row give the
same float32 bits, through autoresets and through ``reset_rows`` mid-episode.
``experiments.batched.run.refusal`` trusts classical ``act_batch`` as exact because of these.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.comms.loss import LossConfig
from openconvoy.core.controllers import HeadingControlConfig, SpeedControlConfig
from openconvoy.core.ladder import LadderConfig
from openconvoy.envs import VectorConvoyEnv
from openconvoy.policies.batched import BatchedClassical
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy
from openconvoy.policies.presets import PRESETS

B, FOLLOWERS = 8, 3


def _custom(base: str, speed: str, heading: str, ladder: bool) -> ClassicalConfig:
    """A preset with another speed law (``pid``: ki 0.2, a small integral limit so the
    clamp is hit) and heading law; ``ladder``: the member's degradation ladder on."""
    cfg = PRESETS[base]
    member = dataclasses.replace(cfg.member, ladder=LadderConfig(enabled=ladder))
    return dataclasses.replace(
        cfg,
        member=member,
        speed=SpeedControlConfig(kind=speed, kp=0.3, ki=0.2, kd=1.1, integral_limit=0.5),
        heading=HeadingControlConfig(kind=heading, gain=0.2),
    )


def _bursts(per: float) -> LossConfig:
    """Gilbert-Elliott loss with 3 s bursts: predecessors go silent past ``stop_after_s``."""
    return LossConfig(per=per, model="gilbert-elliott", mean_burst_s=3.0)


CASES = {
    "paper": (PRESETS["paper"], "paper", _bursts(0.5)),
    "mcacc-rear-weight": (PRESETS["mcacc"], "track", _bursts(0.4)),
    "event-trigger": (PRESETS["platoon-allpred-event"], "paper", LossConfig(per=0.6)),
    "leader-following": (PRESETS["platoon-leader"], "track", _bursts(0.5)),
    "pid-pure-pursuit-ladder": (
        _custom("paper", "pid", "pure-pursuit", True),
        "track",
        LossConfig(per=0.8),
    ),
    "pid-stanley-rear-weight": (_custom("mcacc", "pid", "stanley", True), "track", _bursts(0.6)),
    "pd-pure-pursuit-lookahead": (
        _custom("cacc-lookaheadN", "pd", "pure-pursuit", False),
        "track",
        _bursts(0.5),
    ),
}


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _branches(cfg: ClassicalConfig, obs: np.ndarray) -> tuple[int, int]:
    """Rows this tick with a stale valid target, and with a predecessor heard but lost."""
    lay = cfg.member.layout
    limit = np.float32(cfg.member.fresh_age_s)
    stale = np.zeros(obs.shape[:-1], dtype=bool)
    lost = np.zeros(obs.shape[:-1], dtype=bool)
    for name in lay.targets:
        valid = obs[..., lay.target_offset(name) + 4] > 0.5
        stale |= valid & (obs[..., lay.slot_offset(name) + 5] > limit)
        if name != "leader":
            lost |= ~valid & (obs[..., lay.slot_offset(name) + 6] > 0.5)
    return int(stale.sum()), int(lost.sum())


@pytest.mark.parametrize("case", sorted(CASES))
def test_compiled_act_batch_is_act_bit_for_bit(case: str) -> None:
    cfg, scenario, loss = CASES[case]
    vec = VectorConvoyEnv(
        B, scenario, n_followers=FOLLOWERS, member_config=cfg.member,
        loss=loss, max_time_s=12.0,
    )  # fmt: skip
    compiled, fallback = BatchedClassical(cfg, compiled=True), BatchedClassical(cfg, compiled=False)
    singles = [[ClassicalPolicy(cfg) for _ in range(FOLLOWERS)] for _ in range(B)]
    obs, _ = vec.reset(seed=11)
    actions, stale, lost, resets = [], 0, 0, 0
    for t in range(400):  # 240 ticks per episode: every convoy restarts once
        if t == 120:  # two convoys' controllers forget mid-episode, the others keep theirs
            rows = np.zeros((B, FOLLOWERS), dtype=bool)
            rows[[1, 5]] = True
            compiled.reset_rows(rows)
            fallback.reset_rows(rows)
            for b in (1, 5):
                singles[b] = [ClassicalPolicy(cfg) for _ in range(FOLLOWERS)]
        want = np.array(
            [[singles[b][j].act(obs[b, j]) for j in range(FOLLOWERS)] for b in range(B)]
        )
        np.testing.assert_array_equal(_bits(compiled.act_batch(obs)), _bits(want), err_msg=f"t={t}")
        np.testing.assert_array_equal(_bits(fallback.act_batch(obs)), _bits(want), err_msg=f"t={t}")
        s, lo = _branches(cfg, obs)
        stale, lost = stale + s, lost + lo
        actions.append(want)
        obs, _, term, trunc, _ = vec.step(want)
        done = term | trunc
        if done.any():
            resets += int(done.sum())
            compiled.reset_rows(np.repeat(done[:, None], FOLLOWERS, axis=1))
            fallback.reset_rows(np.repeat(done[:, None], FOLLOWERS, axis=1))
            for b in np.flatnonzero(done):
                for p in singles[b]:
                    p.reset()
    # Not vacuous: the actions move (the paper scenario's road is straight: no steering),
    # and the stale and lost branches were taken.
    acts = np.array(actions)
    assert len(np.unique(acts[..., 0])) > 200
    assert len(np.unique(acts[..., 1])) > (1 if scenario == "track" else 0)
    assert resets >= B and stale > 0 and lost > 0, (resets, stale, lost)


def test_any_batch_shape_and_layout_of_the_input() -> None:
    """``(D,)``, ``(n, D)``, ``(B, F, D)`` and a strided float64 view give the same actions;
    the shape check and its message are the numpy path's."""
    cfg = PRESETS["paper"]
    vec = VectorConvoyEnv(
        4, "track", n_followers=FOLLOWERS, member_config=cfg.member, loss=LossConfig(per=0.3)
    )
    obs, _ = vec.reset(seed=2)
    for _ in range(60):
        obs, *_ = vec.step(BatchedClassical(cfg).act_batch(obs))
    policy = BatchedClassical(cfg)
    assert policy.compiled
    want = policy.act_batch(obs)
    assert want.shape == (4, FOLLOWERS, 2) and want.dtype == np.float32
    assert np.unique(want[..., 0]).size > 4
    flat = obs.reshape(-1, obs.shape[-1])
    np.testing.assert_array_equal(
        _bits(BatchedClassical(cfg).act_batch(flat)), _bits(want.reshape(-1, 2))
    )
    one = BatchedClassical(cfg).act_batch(obs[1, 2])
    assert one.shape == (2,)
    np.testing.assert_array_equal(_bits(one), _bits(want[1, 2]))
    strided = np.repeat(obs, 2, axis=0).astype(np.float64)[::2]
    np.testing.assert_array_equal(_bits(BatchedClassical(cfg).act_batch(strided)), _bits(want))
    with pytest.raises(ValueError, match="observations have 110 features, layout expects 111"):
        policy.act_batch(obs[..., :-1])


def test_without_numba_the_numpy_code_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    """No compiled module (numba not importable): the fallback is chosen quietly, asking
    for the kernel is an error naming the extra."""
    from openconvoy.core.errors import DependencyMissing
    from openconvoy.policies import batched

    monkeypatch.setattr(batched, "_jit", None)
    assert not BatchedClassical(PRESETS["paper"]).compiled
    with pytest.raises(DependencyMissing, match=r"openconvoy\[batched\]"):
        BatchedClassical(PRESETS["paper"], compiled=True)


_FEATURE = st.sampled_from([0.0, 0.5, 1.0]) | st.floats(-40.0, 40.0, width=32)
_CONFIGS = [CASES[name][0] for name in sorted(CASES)]


@settings(max_examples=150, deadline=None)
@given(st.integers(0, len(_CONFIGS) - 1), st.data())
def test_the_rows_are_act_on_random_observations(which: int, data: st.DataObject) -> None:
    """The twin alone (``classical_rows``' walk over the targets, compiled and as Python)
    against ``ClassicalPolicy.act`` on random observations, three ticks in a row so the
    PID integrator carries, and ``reset_rows`` forgetting it before one of them as
    ``ClassicalPolicy.reset`` does: any flag, age, error and path feature, not only what
    an episode reaches."""
    cfg = _CONFIGS[which]
    size = cfg.member.layout.size
    ticks = [
        np.array(data.draw(st.lists(_FEATURE, min_size=size, max_size=size)), dtype=np.float32)
        for _ in range(3)
    ]
    single = ClassicalPolicy(cfg)
    compiled, python = BatchedClassical(cfg, compiled=True), BatchedClassical(cfg, compiled=False)
    assert compiled.compiled and not python.compiled
    forget = data.draw(st.integers(0, 2))  # ``reset_rows`` before that tick: ``reset``
    for k, obs in enumerate(ticks):
        if k == forget:
            single.reset()
            for batched in (compiled, python):
                batched.reset_rows(np.ones((), dtype=bool))
        want = _bits(single.act(obs))
        np.testing.assert_array_equal(_bits(compiled.act_batch(obs)), want)
        np.testing.assert_array_equal(_bits(python.act_batch(obs)), want)
