"""``openconvoy export RUN_DIR --out policy.npz``: a trained policy without torch.

The artifact (``openconvoy.policies.learned.save_npz``) holds the actor's layers as
arrays, the observation normalization, the action scaling, the layout (version, M, k,
size), the member configuration and the control rate; ``load_learned`` runs it with numpy
only. What is exported is the deterministic action SB3's ``predict(deterministic=True)``
returns (``openconvoy.policies.actor``, the same extraction ``load_learned`` runs a
``.zip`` through); the check after an export compares it with SB3's own ``predict``.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from openconvoy.core.errors import InputFileError, MissingFileError
from openconvoy.policies.actor import actor_mlp
from openconvoy.policies.learned import (
    LearnedPolicy,
    load_learned,
    load_npz,
    load_sb3_predict,
    read_zip_meta,
    save_npz,
)
from openconvoy.train.train import POLICY_FILE


def resolve_policy_zip(source: str | Path) -> Path:
    """``source`` itself when a ``.zip``, else ``source/policy.zip`` (a run directory)."""
    path = Path(source)
    if path.is_dir():
        path = path / POLICY_FILE
    if not path.is_file():
        raise MissingFileError(f"no trained policy at {path} (give a run directory or a .zip)")
    if path.suffix != ".zip":
        raise InputFileError(f"{path}: expected an SB3 .zip or a run directory")
    return path


def export_policy(source: str | Path, out: str | Path) -> Path:
    """Export the run directory's (or ``.zip``'s) policy to the numpy-only ``out`` (.npz)."""
    from openconvoy.policies.learned import load_sb3_model

    out = Path(out)
    if out.suffix != ".npz":
        raise InputFileError(f"{out}: the exported policy is a .npz file")
    path = resolve_policy_zip(source)
    meta = read_zip_meta(path)
    model = load_sb3_model(path, meta.algo)
    return save_npz(out, meta, actor_mlp(model))


def max_action_difference(
    zip_policy: LearnedPolicy, npz_policy: LearnedPolicy, observations: np.ndarray
) -> float:
    """Largest absolute difference (SI units) between two policies' actions on
    ``observations`` (rows): how an export is checked against SB3's ``predict``."""
    diffs = [np.max(np.abs(zip_policy.act(o) - npz_policy.act(o))) for o in observations]
    return float(max(diffs, default=0.0))


def verify_export(source: str | Path, npz: str | Path, observations: np.ndarray) -> float:
    """``max_action_difference`` of the trained ``.zip`` (SB3's ``predict``) and its export
    on ``observations``."""
    load_npz(npz)  # a malformed file fails here with its own message
    return max_action_difference(
        load_sb3_predict(resolve_policy_zip(source)), load_learned(npz), observations
    )


def sample_observations(
    policy: LearnedPolicy, n: int = 400, seed: int = 0, per: float = 0.3
) -> np.ndarray:
    """``n`` observations from the ``paper`` scenario driven by ``policy`` at ``per``:
    real inputs (including stale and missing messages) to check an export on."""
    from openconvoy.comms.loss import LossConfig
    from openconvoy.envs import ConvoyEnv

    env = ConvoyEnv(
        "paper",
        member_config=policy.member_config,
        loss=LossConfig(per=per),
        control_rate_hz=policy.control_rate_hz,
    )
    obs, _ = env.reset(seed=seed)
    policies = {a: copy.deepcopy(policy) for a in env.possible_agents}
    out: list[np.ndarray] = []
    while len(out) < n:
        if not env.agents:
            obs, _ = env.reset()
        out.extend(obs.values())
        obs, *_ = env.step({a: policies[a].act(o) for a, o in obs.items()})
    return np.asarray(out[:n], dtype=np.float32)
