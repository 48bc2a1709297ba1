"""The whole tick in one compiled call: ``VectorConvoyEnv.step``'s stages fused.

At small batches a tick costs Python, not the kernels: about ten kernel calls (each
checking the types of its ~20 arguments) and a few dozen numpy operations. ``fused_step``
calls the same kernels in the same order from compiled code, so the numbers are the
same. It covers the common configuration (instant Bernoulli links, a built-in leader
speed profile, no braking fault); the env steps the others stage by stage.

Each stage's arrays come packed once in a tuple in its kernel's argument order
(``pack``): arrays the env updates in place, so the tuples stay valid.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from openconvoy.envs.vector.channel import _bernoulli_deliver, _tx_gate
from openconvoy.envs.vector.jit import bare_kernel, typeof
from openconvoy.envs.vector.leader import _drive, _project
from openconvoy.envs.vector.measures import fill_infos, measure, reported, reward
from openconvoy.envs.vector.member import decide, lead_guard
from openconvoy.envs.vector.observation import observe
from openconvoy.envs.vector.plant import ACCEL, _plant_step


class Stages(NamedTuple):
    """Each stage's arguments of ``fused_step``, after the per-step arrays, in its
    kernel's order (``pack``)."""

    member: tuple[Any, ...]
    lead_project: tuple[Any, ...]
    lead_drive: tuple[Any, ...]
    guard: tuple[Any, ...]
    plant: tuple[Any, ...]
    clock: tuple[Any, ...]
    tx: tuple[Any, ...]
    deliver: tuple[Any, ...]
    observation: tuple[Any, ...]
    meas: tuple[Any, ...]
    score: tuple[Any, ...]
    fill: tuple[Any, ...]


def pack(env: Any) -> Stages:
    """The stages' argument tuples of ``env`` (a ``VectorConvoyEnv``), after the per-step
    arrays: member, leader projection, leader drive, leader guard, plant, clock, Tx gate, delivery,
    observation, measures, reward, infos."""
    t, own, rx, ch, ld, pl = (
        env.t,
        env._own,  # with the heading's cosine and sine
        env.rx,
        env.channel,
        env.leader,
        env.plant,
    )
    return Stages(
        (t, own, env.ranging.reading, env.pred_est, env._member, env._commands),
        (own, ld.road),
        (t, own, ld.road, env.cmd_v, env.cmd_dh),
        (t, own, env._member, env._commands),
        (pl.arrays, env._cmd_v_flat, env._cmd_dh_flat, pl.dt),
        (t, env.step_count, env.dt, env.max_steps, env._has_cmd, env._accel_old, own),
        (t, env._everyone, own, ch.gate),
        (ch.draws, ch.send, ch.pairs, env._everyone, t, own, ch.counts, rx.pushed),
        (env._everyone, t, own, env._sources, env._measures),
        (own, env._half_sum, env.gap, env.collided),
        (env.gap, env.desired_gap, env._accel_old, own, env.collided, 1.0 / env.dt,
         env._reward_c),
        (reported(env, own),),
    )  # fmt: skip


class FusedCall:
    """``fused_step`` for one env, called through the compiled entry point of its
    signature once the first call has typed it: the dispatcher types every argument
    (~170 arrays in nested tuples) on every call, ~10 µs a tick. An env's stage tuples
    are fixed and its per-step arrays always of the same kinds, so one typing holds."""

    def __init__(self) -> None:
        self._entry: Any = None

    def __call__(self, *args: Any) -> None:
        if self._entry is not None:
            self._entry(*args)
            return
        fused_step(*args)
        sig = tuple(typeof(a) for a in args)
        found = fused_step.overloads.get(sig)
        # (``entry_point``: numba's compiled wrapper; the dispatcher stays if it is absent)
        self._entry = getattr(found, "entry_point", None) or fused_step


@bare_kernel
def fused_step(act, obs, rewards, terminated, truncated, info, st):  # pragma: no cover - compiled
    """Twin of ``ConvoyEnv.step`` (the clock, terminations and truncations of
    ``VectorConvoyEnv._staged_step``) for every convoy: decide, drive the leaders, move the plant, advance the
    clock, Tx gates, loss and delivery, observations, gaps, rewards, terminations and the
    info arrays (``info``: ``fill_infos``'s four outputs), each stage's arguments in
    ``st`` (``Stages``)."""
    decide(act, *st.member)
    _project(*st.lead_project)
    _drive(*st.lead_drive)
    lead_guard(*st.guard)
    t, step_count, dt, max_steps, has_cmd, accel_old, own = st.clock
    B = t.shape[0]
    for b in range(B):
        has_cmd[b] = True
        for i in range(own.shape[2]):
            accel_old[b, i] = own[ACCEL, b, i]
    _plant_step(*st.plant)
    for b in range(B):
        step_count[b] += 1
        t[b] = step_count[b] * dt
    _tx_gate(*st.tx)
    _bernoulli_deliver(*st.deliver)
    observe(obs, *st.observation)
    measure(*st.meas)
    reward(rewards, *st.score)
    gap, collided = st.meas[2], st.meas[3]
    for b in range(B):
        hit = False
        for f in range(gap.shape[1]):
            hit = hit or collided[b, f]
        terminated[b] = hit
        truncated[b] = step_count[b] >= max_steps and not hit
    fill_infos(info, *st.fill)
