"""``openconvoy export RUN_DIR --out policy.npz``: a trained policy without torch.

The artifact (``openconvoy.policies.learned.save_npz``) holds the actor's layers as
arrays, the observation normalization, the action scaling, the layout (version, M, k,
size), the member configuration and the control rate; ``load_learned`` runs it with numpy
only. What is exported is the deterministic action SB3's ``predict(deterministic=True)``
returns: PPO's Gaussian mean clipped to [-1, 1] (gSDE or not; tanh-squashed with
squash_output), SAC's tanh-squashed mean.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from openconvoy.core.errors import InputFileError, MissingFileError
from openconvoy.policies.learned import (
    LearnedPolicy,
    NumpyMLP,
    load_learned,
    load_npz,
    read_zip_meta,
    save_npz,
)
from openconvoy.train.train import POLICY_FILE

_ACTIVATION_CLASSES = {"Tanh": "tanh", "ReLU": "relu", "ELU": "elu", "LeakyReLU": "leaky_relu"}


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


def _layers(modules, where: str) -> tuple[list[np.ndarray], list[np.ndarray], str | None]:
    """Weights, biases and the (single) activation of a sequence of torch modules."""
    import torch.nn as nn

    weights, biases, activation = [], [], None
    for m in modules:
        if isinstance(m, nn.Linear):
            weights.append(m.weight.detach().cpu().numpy().astype(np.float64))
            bias = m.bias.detach().cpu().numpy() if m.bias is not None else np.zeros(m.out_features)
            biases.append(bias.astype(np.float64))
        elif type(m).__name__ in _ACTIVATION_CLASSES:
            if isinstance(m, nn.LeakyReLU) and m.negative_slope != 0.01:
                raise InputFileError(
                    f"{where}: LeakyReLU slope {m.negative_slope} is not exportable (0.01 is)"
                )
            name = _ACTIVATION_CLASSES[type(m).__name__]
            if activation not in (None, name):
                raise InputFileError(
                    f"{where}: mixed activations {activation} and {name} are not exportable"
                )
            activation = name
        elif isinstance(m, (nn.Flatten, nn.Identity)):
            continue
        else:
            raise InputFileError(f"{where}: layer {type(m).__name__} is not exportable")
    return weights, biases, activation


def actor_mlp(model) -> NumpyMLP:
    """The deterministic actor of an SB3 PPO or SAC model as a ``NumpyMLP``."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.torch_layers import FlattenExtractor

    if isinstance(model, PPO):
        policy = model.policy
        if not isinstance(policy.pi_features_extractor, FlattenExtractor):
            raise InputFileError("only PPO MlpPolicy (flat observations) is exportable")
        # gSDE changes only the exploration noise: the deterministic action is the Gaussian
        # mean (SB3 StateDependentNoiseDistribution.mode), tanh-squashed with squash_output
        # (then ``predict`` unscales it from [-1, 1], as SAC's is).
        hidden = list(policy.mlp_extractor.policy_net)
        head = [policy.action_net]
        output = "tanh" if policy.squash_output else "clip"
    elif isinstance(model, SAC):
        actor = model.policy.actor
        if not isinstance(actor.features_extractor, FlattenExtractor) or actor.use_sde:
            # SB3 clips SAC's gSDE mean with a Hardtanh before the tanh, a head the .npz
            # format does not hold; `openconvoy train` never makes such a SAC.
            raise InputFileError("only SAC MlpPolicy without gSDE is exportable")
        hidden = list(actor.latent_pi)
        head = [actor.mu]
        output = "tanh"
    else:
        raise InputFileError(
            f"cannot export a {type(model).__name__} model (PPO and SAC are exportable)"
        )
    w, b, activation = _layers(hidden, type(model).__name__)
    hw, hb, _ = _layers(head, type(model).__name__)
    return NumpyMLP(w + hw, b + hb, activation or "identity", output)


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
    """``max_action_difference`` of the trained ``.zip`` and its export on ``observations``."""
    load_npz(npz)  # a malformed file fails here with its own message
    return max_action_difference(
        load_learned(resolve_policy_zip(source)), load_learned(npz), observations
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
