"""The batched env's per-tick measures: gaps, collisions, rewards (``envs.reward``'s
terms, the same order of operations) and the info arrays."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from openconvoy.envs import reward as reward_mod
from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.vector.jit import bare_kernel, rules
from openconvoy.envs.vector.math import norm
from openconvoy.envs.vector.plant import ACCEL, SPEED, YAW_RATE, X, Y

rules(reward_mod, "follower_reward")


def pack_reward(c: RewardConfig) -> np.ndarray:
    """``RewardConfig`` as the kernel's array."""
    return np.array(c.numbers)


@bare_kernel
def measure(own, half_sum, gap, collided):  # pragma: no cover - compiled
    """Centre-to-centre gap of each follower to the vehicle ahead (m), and collisions
    (``ConvoyWorld.measure``)."""
    for b in range(gap.shape[0]):
        for f in range(gap.shape[1]):
            g = norm(own[X, b, f] - own[X, b, f + 1], own[Y, b, f] - own[Y, b, f + 1])
            gap[b, f] = g
            collided[b, f] = g < half_sum[f]


@bare_kernel
def reward(out, gap, desired, accel_old, own, collided, inv_dt, c):  # pragma: no cover
    """``envs.reward``: spacing, acceleration, jerk, yaw rate and collision terms."""
    for b in range(gap.shape[0]):
        for f in range(gap.shape[1]):
            i = f + 1
            accel = own[ACCEL, b, i]
            jerk = (accel - accel_old[b, i]) * inv_dt
            error = gap[b, f] - desired[b, i]
            hit = collided[b, f]
            out[b, f] = reward_mod.follower_reward(c, error, accel, jerk, own[YAW_RATE, b, i], hit)


FLOAT_KEYS = (
    "gap_m", "desired_gap_m", "platooning_error_m", "spacing_error_m", "speed_mps",
    "accel_mps2", "cmd_speed_mps", "cmd_heading_change_rad", "pred_msg_age_s",
)  # fmt: skip
INT_KEYS = (
    "mode", "msgs_sent", "msgs_received", "msgs_kept", "msgs_lost", "policy_errors",
    "msgs_offered",
)  # fmt: skip
"""(B, N-1) each. ``msgs_received``/``msgs_lost``: what the channel delivered to / dropped
for the vehicle on the links counted (``VectorConvoyEnv``'s ``link_counters``: the links it
keeps, or every other vehicle's); ``msgs_kept``: those deliveries its Rx gate kept;
``msgs_offered``: the messages every other vehicle broadcast so far (what an all-pairs
channel offered it: ``msgs_received + msgs_lost`` plus those in flight, under ``"all"``)."""
LEADER_FLOAT_KEYS = ("leader_cmd_speed_mps", "leader_cmd_heading_change_rad")
LEADER_INT_KEYS = (
    "leader_mode", "leader_msgs_sent", "leader_msgs_received", "leader_msgs_lost",
    "leader_msgs_offered",
)  # fmt: skip


class Reported(NamedTuple):
    """What ``fill_infos`` reads, (B, N) unless said: the gaps (m, (B, N-1)), desired gaps
    and spacing errors (m), the own states ``own`` (the plant's rows), the commands
    ``cmd_v`` (m/s) and ``cmd_dh`` (rad), whether a command was given ``has_cmd`` (B,), the
    predecessor's age ``pred_age`` (s), the ladder's ``modes``, the messages ``sent``,
    ``received``, ``kept`` and ``lost``, and the policy's ``errors``."""

    gap: np.ndarray
    desired: np.ndarray
    spacing_error: np.ndarray
    own: np.ndarray
    cmd_v: np.ndarray
    cmd_dh: np.ndarray
    has_cmd: np.ndarray
    pred_age: np.ndarray
    modes: np.ndarray
    sent: np.ndarray
    received: np.ndarray
    kept: np.ndarray
    lost: np.ndarray
    errors: np.ndarray


def reported(env: Any, own: np.ndarray) -> Reported:
    """``fill_infos``'s inputs of ``env`` (a ``VectorConvoyEnv``) with own states ``own``."""
    ch = env.channel
    return Reported(
        env.gap, env.desired_gap, env.spacing_error, own, env.cmd_v, env.cmd_dh, env._has_cmd,
        env.pred_age, env.modes, ch.msgs_sent, ch.delivered_to, ch.msgs_kept, ch.lost_to,
        env.policy_errors,
    )  # fmt: skip


def info_arrays(B: int, F: int) -> tuple[np.ndarray, ...]:
    """``fill_infos``'s outputs for ``B`` convoys of ``F`` followers, uninitialized."""
    return (
        np.empty((len(FLOAT_KEYS), B, F)),
        np.empty((len(INT_KEYS), B, F), dtype=np.int64),
        np.empty((len(LEADER_FLOAT_KEYS), B)),
        np.empty((len(LEADER_INT_KEYS), B), dtype=np.int64),
    )


def infos(env: Any, filled: tuple[np.ndarray, ...] | None = None) -> dict[str, Any]:
    """Arrays (B, N-1) of ``ConvoyEnv``'s info keys (NaN where it has None), plus ``mode``
    codes (``vector.env.MODES``); ``t_s`` and ``leader_*`` (B,): the leader's values of
    the keys a log row has (``experiments.batched.run`` writes the leader's rows from them).
    ``filled``: ``info_arrays`` that ``fill_infos`` has filled this tick already."""
    if filled is None:
        filled = info_arrays(*env.gap.shape)
        fill_infos(filled, reported(env, env.own))
    fl, it, lf, li = filled
    out = dict(zip(FLOAT_KEYS, fl))
    out.update(zip(INT_KEYS, it))
    out.update(zip(LEADER_FLOAT_KEYS, lf))
    out.update(zip(LEADER_INT_KEYS, li))
    out["t_s"] = env.t.copy()
    out["leader_speed_mps"] = env.own[SPEED][:, 0].copy()
    out["collision"] = env.collided.copy()
    return out


@bare_kernel
def fill_infos(out, rep):  # pragma: no cover - compiled
    """``envs.convoy_env.agent_infos``'s values of ``rep`` (``Reported``) into
    ``info_arrays`` ``out`` (floats, ints, the leader's floats and ints): ``infos``'s keys
    in their order, NaN where ``agent_infos`` has None; ``msgs_offered``: the column sums
    of ``Channel.sent``."""
    fl, it, lf, li = out
    gap, desired, spacing_error, own = rep.gap, rep.desired, rep.spacing_error, rep.own
    cmd_v, cmd_dh, has_cmd, pred_age, modes = (
        rep.cmd_v,
        rep.cmd_dh,
        rep.has_cmd,
        rep.pred_age,
        rep.modes,
    )
    sent, received, kept, lost, errors = rep.sent, rep.received, rep.kept, rep.lost, rep.errors
    for b in range(gap.shape[0]):
        total = 0  # every vehicle's broadcasts: msgs_offered in closed form
        for i in range(sent.shape[1]):
            total += sent[b, i]
        lf[0, b] = cmd_v[b, 0] if has_cmd[b] else np.nan
        lf[1, b] = cmd_dh[b, 0] if has_cmd[b] else np.nan
        li[0, b], li[1, b], li[2, b], li[3, b] = modes[b, 0], sent[b, 0], received[b, 0], lost[b, 0]
        li[4, b] = total - sent[b, 0]
        for f in range(gap.shape[1]):
            i = f + 1
            fl[0, b, f], fl[1, b, f] = gap[b, f], desired[b, i]
            fl[2, b, f], fl[3, b, f] = abs(gap[b, f] - desired[b, i]), spacing_error[b, i]
            fl[4, b, f], fl[5, b, f] = own[SPEED, b, i], own[ACCEL, b, i]
            fl[6, b, f] = cmd_v[b, i] if has_cmd[b] else np.nan
            fl[7, b, f] = cmd_dh[b, i] if has_cmd[b] else np.nan
            fl[8, b, f] = pred_age[b, i]
            it[0, b, f], it[1, b, f], it[2, b, f] = modes[b, i], sent[b, i], received[b, i]
            it[3, b, f], it[4, b, f], it[5, b, f] = kept[b, i], lost[b, i], errors[b, i]
            it[6, b, f] = total - sent[b, i]
