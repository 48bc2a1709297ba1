"""Policies: classical ones composed from core parts, presets, learned-policy loaders, specs."""

from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy
from openconvoy.policies.presets import PRESETS
from openconvoy.policies.spec import load_policy

__all__ = ["ClassicalConfig", "ClassicalPolicy", "PRESETS", "load_policy"]
