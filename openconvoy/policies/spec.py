"""Policy specs: one grammar everywhere (``sim``, ``experiment``, ``deploy``, ``train``).

``--policy X`` where X is

- a preset name (``openconvoy presets`` lists them), optionally with ``+ladder`` to switch
  the staleness ladder on (``paper+ladder``);
- a TOML file describing a classical policy (what ``openconvoy tune`` writes; see
  ``classical_from_toml``);
- a stable-baselines3 ``.zip`` or an exported ``.npz`` (learned policies).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openconvoy.core.config import dumps_toml, from_dict, load_toml, to_dict
from openconvoy.core.errors import ConfigError, MissingFileError
from openconvoy.core.policy import ConvoyPolicy, as_convoy_policy
from openconvoy.policies.classical import ClassicalConfig, ClassicalPolicy
from openconvoy.policies.presets import PRESETS, with_ladder

LADDER_SUFFIX = "+ladder"
LEARNED_SUFFIXES = (".zip", ".npz")


@dataclass(frozen=True)
class PolicySpec:
    """A ``--policy`` spec, parsed (the one place that reads the grammar): ``base`` is a
    preset name or a file path, ``ladder`` whether ``+ladder`` follows it."""

    base: str
    ladder: bool = False

    @classmethod
    def parse(cls, spec: str) -> PolicySpec:
        if spec.endswith(LADDER_SUFFIX):
            return cls(spec[: -len(LADDER_SUFFIX)], True)
        return cls(spec)

    @property
    def suffix(self) -> str:
        """``"+ladder"`` or ``""``: what follows the base."""
        return LADDER_SUFFIX if self.ladder else ""

    @property
    def learned(self) -> bool:
        """An SB3 ``.zip`` or exported ``.npz`` (a learned policy takes no ``+ladder``)."""
        return not self.ladder and Path(self.base).suffix in LEARNED_SUFFIXES

    @property
    def toml(self) -> bool:
        """A classical policy file."""
        return self.base.endswith(".toml")

    def with_base(self, base: str) -> PolicySpec:
        return PolicySpec(base, self.ladder)

    def __str__(self) -> str:
        return self.base + self.suffix


def load_policy(spec: str, **learned_kwargs: Any) -> ConvoyPolicy:
    """The policy a spec names (a ``ConvoyPolicy``: checked here, so callers read its
    ``member_config``, ``control_rate_hz`` and ``name`` directly). Learned-policy keyword
    arguments pass to their loader."""
    parsed = PolicySpec.parse(spec)
    if parsed.learned:
        path = Path(parsed.base)
        if not path.is_file():
            raise MissingFileError(f"policy file not found: {spec}")
        from openconvoy.policies import learned

        return as_convoy_policy(learned.load_learned(path, **learned_kwargs), spec)
    config = classical_config(spec)
    if config.mpc is not None:
        from openconvoy.policies.mpc import MPCPolicy

        return as_convoy_policy(MPCPolicy(config), spec)
    return as_convoy_policy(ClassicalPolicy(config), spec)


def classical_config(spec: str) -> ClassicalConfig:
    """The ClassicalConfig of a preset name (with optional ``+ladder``) or TOML file."""
    parsed = PolicySpec.parse(spec)
    base = parsed.base
    if parsed.toml:
        config = classical_from_toml(base)
    elif base in PRESETS:
        config = PRESETS[base]
    else:
        raise ConfigError(
            f"unknown policy {spec!r}: not a preset ({', '.join(PRESETS)}), "
            "nor a .toml, .zip or .npz file"
        )
    return with_ladder(config) if parsed.ladder else config


def classical_from_toml(path: str | Path) -> ClassicalConfig:
    """Load a classical policy file: a ``[policy]`` table with ClassicalConfig's keys, and
    optionally ``base = "<preset>"`` whose values the file's override, table by table."""
    data = load_toml(path)
    table = data.get("policy")
    if table is None or set(data) - {"policy"}:
        raise ConfigError(f"{path}: a policy file has exactly one top-level table, [policy]")
    return classical_from_table(table, Path(path).stem, f"{path}: policy", Path(path).name)


def classical_from_table(table: Any, name: str, where: str, source: str = "") -> ClassicalConfig:
    """A ClassicalConfig from a ``[policy]`` table (its ``base`` preset overridden by the
    table, table by table); errors name ``where`` and the key."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table, got {table!r}")
    table = dict(table)
    base_name = table.pop("base", None)
    if base_name is not None:
        if base_name not in PRESETS:
            raise ConfigError(
                f"{where}.base: unknown base preset {base_name!r}; expected one of {', '.join(PRESETS)}"
            )
        inherited = to_dict(PRESETS[base_name])
        inherited["name"] = name
        inherited["description"] = f"{base_name} with changes from {source or name}"
        table = _merge(inherited, table)
    table.setdefault("name", name)
    return from_dict(ClassicalConfig, table, where)


def classical_to_toml(config: ClassicalConfig) -> str:
    """A policy file that ``classical_from_toml`` reads back to ``config``."""
    return dumps_toml({"policy": to_dict(config)})


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def describe(config: ClassicalConfig) -> str:
    """One line: name, topology, trigger, spacing, controllers."""
    m = config.member
    return (
        f"{config.name}: {m.topology}, {m.trigger.kind}, {m.spacing.kind}, "
        f"{'mpc' if config.mpc is not None else config.speed.kind} + {config.heading.kind}"
        + (", ladder" if m.ladder.enabled else "")
    )


__all__ = [
    "load_policy",
    "classical_config",
    "classical_from_toml",
    "classical_to_toml",
    "describe",
]
