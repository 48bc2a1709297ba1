"""The batched env's per-tick measures: gaps, collisions, rewards (``envs.reward``'s
terms, the same order of operations) and the info arrays."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from openconvoy.envs.reward import RewardConfig
from openconvoy.envs.vector_jit import kernel
from openconvoy.envs.vector_trail import norm


def pack_reward(c: RewardConfig) -> np.ndarray:
    """``RewardConfig`` as the kernel's array."""
    return np.array(
        [c.spacing_scale_m, c.accel_scale_mps2, c.jerk_scale_mps3, c.yaw_rate_scale_radps,
         c.w_spacing, c.w_accel, c.w_jerk, c.w_yaw_rate, c.collision_penalty],
    )  # fmt: skip


@kernel
def measure(own, half_sum, gap, collided):  # pragma: no cover - compiled
    """Centre-to-centre gap of each follower to the vehicle ahead (m), and collisions."""
    for b in range(gap.shape[0]):
        for f in range(gap.shape[1]):
            g = norm(own[0, b, f] - own[0, b, f + 1], own[1, b, f] - own[1, b, f + 1])
            gap[b, f] = g
            collided[b, f] = g < half_sum[f]


@kernel
def reward(gap, desired, accel_old, own, collided, inv_dt, c, out):  # pragma: no cover
    """``envs.reward``: spacing, acceleration, jerk, yaw rate and collision terms."""
    for b in range(gap.shape[0]):
        for f in range(gap.shape[1]):
            i = f + 1
            e = abs(gap[b, f] - desired[b, i]) / c[0]
            e = 0.0 if math.isnan(e) else min(e, 1.0)
            a = own[4, b, i] / c[1]
            j = (own[4, b, i] - accel_old[b, i]) * inv_dt / c[2]
            w = own[5, b, i] / c[3]
            pen = c[8] if collided[b, f] else 0.0
            out[b, f] = -(c[4] * e + c[5] * a * a + c[6] * j * j + c[7] * w * w + pen)


def infos(env: Any) -> dict[str, np.ndarray]:
    """Arrays (B, N-1) of ``ConvoyEnv``'s info keys (NaN where it has None), plus ``mode``
    codes (``vector_env.MODES``), ``t_s`` (B,)."""
    nan_cmd = ~env._has_cmd[:, None]
    ch = env.channel
    return {
        "t_s": env.t.copy(),
        "gap_m": env.gap.copy(),
        "desired_gap_m": env.desired_gap[:, 1:].copy(),
        "platooning_error_m": np.abs(env.gap - env.desired_gap[:, 1:]),
        "spacing_error_m": env.spacing_error[:, 1:].copy(),
        "speed_mps": env.own[2][:, 1:].copy(),
        "accel_mps2": env.own[4][:, 1:].copy(),
        "leader_speed_mps": env.own[2][:, 0].copy(),
        "cmd_speed_mps": np.where(nan_cmd, np.nan, env.cmd_v[:, 1:]),
        "cmd_heading_change_rad": np.where(nan_cmd, np.nan, env.cmd_dh[:, 1:]),
        "mode": env.modes[:, 1:].copy(),
        "collision": env.collided.copy(),
        "msgs_sent": ch.msgs_sent[:, 1:].copy(),
        "msgs_received": ch.delivered_to[:, 1:].copy(),
        "msgs_kept": ch.msgs_kept[:, 1:].copy(),
        "msgs_lost": ch.lost_to[:, 1:].copy(),
        "pred_msg_age_s": env.pred_age[:, 1:].copy(),
        "policy_errors": env.policy_errors[:, 1:].copy(),
    }
