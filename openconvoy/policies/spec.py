"""Policy specs: one grammar everywhere (``sim``, ``experiment``, ``tune``, ``deploy``,
``demo``, ``train``).

``--policy X`` where X is

- a preset name (``openconvoy presets`` lists them), optionally with ``+ladder`` to switch
  the staleness ladder on (``paper+ladder``);
- a TOML file describing a classical policy (what ``openconvoy tune`` writes; see
  ``classical_from_toml``), whose components may name plug-ins (``kind =
  "mylab.spacing:Quadratic"`` with a ``params`` table), or a plug-in policy with its
  arguments (``[policy] plugin = "mylab.ctl:Mine"`` and ``[policy.args]``);
- a Python plug-in ``module.path:Name`` or ``path/to/file.py:Name``, or the name an
  installed package registers (``openconvoy.policies`` entry point), with keyword
  arguments as ``?key=value&key=value`` (what ``--policy-arg key=value`` adds;
  ``policies.plugin``);
- a stable-baselines3 ``.zip`` or an exported ``.npz`` (learned policies).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openconvoy.core import plugins
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
        """A policy file (classical, or naming a plug-in)."""
        return plugins.split_args(self.base)[0].endswith(".toml")

    @property
    def plugin(self) -> bool:
        """A Python plug-in: ``module:Name``, ``file.py:Name`` or an installed name
        (``openconvoy.policies`` entry point) that is no preset."""
        ref = plugins.split_args(self.base)[0]
        if plugins.is_reference(ref):
            return True
        return ref not in PRESETS and not self.toml and ref in plugins.entry_points("policy")

    @property
    def plugin_file(self) -> str | None:
        """The ``.py`` file a ``file.py:Name`` spec names (None otherwise)."""
        return plugins.file_of(self.base)

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
    plugin = plugin_of(spec)
    if plugin is not None:
        from openconvoy.policies.plugin import load_plugin_policy

        ref, kwargs, label = plugin
        return as_convoy_policy(load_plugin_policy(ref, kwargs, label), spec)
    config = classical_config(spec)
    if config.mpc is not None:
        from openconvoy.policies.mpc import MPCPolicy

        return as_convoy_policy(MPCPolicy(config), spec)
    return as_convoy_policy(ClassicalPolicy(config), spec)


def plugin_of(spec: str) -> tuple[str, dict[str, Any], str] | None:
    """``(reference, keyword arguments, label)`` of a spec naming a whole-policy plug-in
    (directly, or by a policy TOML's ``plugin`` key), else None."""
    parsed = PolicySpec.parse(spec)
    table = None
    if parsed.toml and not parsed.ladder:
        base, args = plugins.split_args(parsed.base)
        if args:
            table = _plugin_table(base)
            if table is None:
                raise ConfigError(f"{spec}: ?key=value arguments are for plug-in policies")
            ref, kwargs = table[0], {**table[1], **args}
            return ref, kwargs, Path(base).stem
        table = _plugin_table(parsed.base)
        if table is not None:
            return table[0], table[1], Path(parsed.base).stem
        return None
    if parsed.toml and _plugin_table(plugins.split_args(parsed.base)[0]) is not None:
        raise ConfigError(
            f"{spec}: +ladder is for classical policies; a plug-in policy sets the ladder in its member_config"
        )
    if not parsed.plugin:
        return None
    if parsed.ladder:
        raise ConfigError(
            f"{spec}: +ladder is for classical policies; a plug-in policy sets the ladder in its member_config"
        )
    return parsed.base, {}, plugins.split_args(parsed.base)[0]


def _plugin_table(path: str) -> tuple[str, dict[str, Any]] | None:
    """A policy file's ``(plugin, args)`` when its ``[policy]`` names a plug-in, else None."""
    data = load_toml(path)
    table = data.get("policy")
    if not isinstance(table, dict) or "plugin" not in table:
        return None
    return plugin_from_table(table, f"{path}: policy")


def plugin_from_table(table: dict[str, Any], where: str) -> tuple[str, dict[str, Any]]:
    """``(plugin, args)`` of a ``[policy]`` table naming a plug-in: ``plugin`` and an
    optional ``args`` table (the keyword arguments), nothing else."""
    unknown = sorted(set(table) - {"plugin", "args", "name", "description"})
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)} beside plugin; a plug-in policy's "
            "keyword arguments go in [policy.args]"
        )
    ref, args = table["plugin"], table.get("args", {})
    if not isinstance(ref, str) or not isinstance(args, dict):
        raise ConfigError(f"{where}: plugin is a string (module:Name) and args a table")
    return ref, dict(args)


def with_policy_args(spec: str, args: list[str] | None) -> str:
    """``spec`` with ``--policy-arg key=value`` arguments folded in (``?key=value``), so
    they travel with the spec to every run and worker."""
    if not args:
        return spec
    parsed = PolicySpec.parse(spec)
    if parsed.ladder or not (parsed.plugin or plugin_of(spec) is not None):
        raise ConfigError(f"--policy-arg: {spec} is not a Python plug-in policy")
    values: dict[str, Any] = {}
    for item in args:
        key, eq, text = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise ConfigError(f"--policy-arg: {item!r} is not key=value")
        values[key.strip()] = plugins.parse_value(text.strip())
    return plugins.join_args(spec, values)


def classical_config(spec: str) -> ClassicalConfig:
    """The ClassicalConfig of a preset name (with optional ``+ladder``) or TOML file."""
    parsed = PolicySpec.parse(spec)
    base = parsed.base
    if parsed.toml:
        config = classical_from_toml(base)
    elif base in PRESETS:
        config = PRESETS[base]
    elif parsed.plugin:
        raise ConfigError(f"{spec} is a Python plug-in policy, not a classical one")
    else:
        raise ConfigError(
            f"unknown policy {spec!r}: not a preset ({', '.join(PRESETS)}), an installed "
            "plug-in, module:Name, file.py:Name, nor a .toml, .zip or .npz file"
        )
    return with_ladder(config) if parsed.ladder else config


def classical_from_toml(path: str | Path) -> ClassicalConfig:
    """Load a classical policy file: a ``[policy]`` table with ClassicalConfig's keys, and
    optionally ``base = "<preset>"`` whose values the file's override, table by table."""
    data = load_toml(path)
    table = data.get("policy")
    if table is None or set(data) - {"policy"}:
        raise ConfigError(f"{path}: a policy file has exactly one top-level table, [policy]")
    if isinstance(table, dict) and "plugin" in table:
        raise ConfigError(
            f"{path}: names a plug-in policy ({table['plugin']}), not a classical one"
        )
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
    return from_dict(ClassicalConfig, _shorthands(table), where)


_COMPONENT_TABLES = (("member", "spacing"), ("member", "trigger"), ("speed",), ("heading",))


def _shorthands(table: dict[str, Any]) -> dict[str, Any]:
    """``spacing = "mylab.spacing:Quadratic"`` (a string where a component's table goes)
    as ``[spacing] kind = "..."``, for the member's spacing and trigger and the controllers."""
    out = dict(table)
    for path in _COMPONENT_TABLES:
        parent = out
        for key in path[:-1]:
            if not isinstance(parent.get(key), dict):
                break
            parent[key] = parent = dict(parent[key])
        else:
            if isinstance(parent.get(path[-1]), str):
                parent[path[-1]] = {"kind": parent[path[-1]]}
    return out


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
    "plugin_of",
    "with_policy_args",
    "classical_config",
    "classical_from_toml",
    "classical_to_toml",
    "describe",
]
