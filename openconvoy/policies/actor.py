"""The deterministic actor of an SB3 PPO or SAC model as a numpy ``NumpyMLP``.

Both the export (``openconvoy export``) and the loading of a trained ``.zip``
(``openconvoy.policies.learned.load_learned``) extract the actor here, once, so a ``.zip``
runs in sim and sweeps through the very numpy forward its ``.npz`` runs on a vehicle: the
two give the same numbers to the bit. What is extracted is the action SB3's
``predict(deterministic=True)`` returns: PPO's Gaussian mean clipped to [-1, 1] (gSDE or
not; tanh-squashed with ``squash_output``), SAC's tanh-squashed mean (with gSDE, clipped to
±``clip_mean`` first, as SB3's Hardtanh does). Imports torch and
stable-baselines3 lazily (the ``train`` extra); the vehicle runtime never calls it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from openconvoy.core.errors import InputFileError
from openconvoy.policies.learned import NumpyMLP

ACTIVATION_CLASSES = {"Tanh": "tanh", "ReLU": "relu", "ELU": "elu", "LeakyReLU": "leaky_relu"}
"""torch activation classes the numpy forward knows, by their ``ACTIVATIONS`` name."""


def torch_layers(modules: Any, where: str) -> tuple[list[np.ndarray], list[np.ndarray], str | None]:
    """Weights and biases (float64) and the single activation of a sequence of torch modules;
    an ``InputFileError`` naming ``where`` for anything the numpy forward cannot hold."""
    import torch.nn as nn

    weights, biases, activation = [], [], None
    for m in modules:
        if isinstance(m, nn.Linear):
            weights.append(m.weight.detach().cpu().numpy().astype(np.float64))
            bias = m.bias.detach().cpu().numpy() if m.bias is not None else np.zeros(m.out_features)
            biases.append(bias.astype(np.float64))
        elif type(m).__name__ in ACTIVATION_CLASSES:
            if isinstance(m, nn.LeakyReLU) and m.negative_slope != 0.01:
                raise InputFileError(
                    f"{where}: LeakyReLU slope {m.negative_slope} is not exportable (0.01 is)"
                )
            name = ACTIVATION_CLASSES[type(m).__name__]
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


def actor_mlp(model: Any) -> NumpyMLP:
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
        head, mean_clip = [policy.action_net], 0.0
        output = "tanh" if policy.squash_output else "clip"
    elif isinstance(model, SAC):
        actor = model.policy.actor
        if not isinstance(actor.features_extractor, FlattenExtractor):
            raise InputFileError("only SAC MlpPolicy (flat observations) is exportable")
        hidden = list(actor.latent_pi)
        head, mean_clip = sac_head(actor.mu)
        output = "tanh"
    else:
        raise InputFileError(
            f"cannot export a {type(model).__name__} model (PPO and SAC are exportable)"
        )
    w, b, activation = torch_layers(hidden, type(model).__name__)
    hw, hb, _ = torch_layers(head, type(model).__name__)
    return NumpyMLP(w + hw, b + hb, activation or "identity", output, mean_clip)


def sac_head(mu: Any) -> tuple[list[Any], float]:
    """SAC's mean layer as (linear modules, mean clip): with gSDE SB3 appends a symmetric
    ``Hardtanh(-clip_mean, clip_mean)`` to it (``clip_mean`` 0: none); 0.0 without one."""
    import torch.nn as nn

    modules = list(mu) if isinstance(mu, nn.Sequential) else [mu]
    if modules and isinstance(modules[-1], nn.Hardtanh):
        clip = modules.pop()
        low, high = float(clip.min_val), float(clip.max_val)  # type: ignore[arg-type]
        if low != -high or high <= 0:
            raise InputFileError(
                f"SAC: mean clip [{low}, {high}] is not symmetric; "
                "the numpy forward clips to ±clip_mean"
            )
        return modules, high
    return modules, 0.0


__all__ = ["ACTIVATION_CLASSES", "actor_mlp", "sac_head", "torch_layers"]
