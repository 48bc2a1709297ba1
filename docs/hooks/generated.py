"""MkDocs hook: the tables of the environments page, generated from the code at build time.

A page asks for a table with a marker ``<!-- generated: NAME -->`` (on a line of its own,
indented as the table should be, or inline for a short list); the hook replaces it with the
text ``NAME`` built from the package itself (the observation layout of
``openconvoy.core.observation``, the environments' Gymnasium spaces, ``RewardConfig``,
``INFO_KEYS``), so the documentation cannot drift from the code: an unknown marker, or an
observation feature without a description below, fails the build.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from typing import Any

BLOCK = re.compile(r"^([ \t]*)<!-- generated: ([a-z-]+) -->[ \t]*$", re.MULTILINE)
INLINE = re.compile(r"<!-- generated: ([a-z-]+) -->")

# What each observation feature means (units in parentheses). A feature the layout gains without
# a line here stops the docs build, so this stays complete.
FEATURE_DOCS: dict[tuple[str, str], str] = {
    ("state", "dx"): "position of that vehicle ahead (+) or behind (−) the ego, ego frame (m)",
    ("state", "dy"): "position of that vehicle to the ego's left (+), ego frame (m)",
    ("state", "dheading"): "its heading minus the ego's, wrapped to [−π, π] (rad)",
    ("state", "speed"): "its speed as broadcast (m/s)",
    ("state", "accel"): "its acceleration as broadcast (m/s²)",
    ("state", "age"): "message age: now − the sender's measurement time, clipped (s)",
    ("state", "valid"): "1 when this entry holds a received state, else 0 (entry zeroed)",
    ("own", "speed"): "the ego's speed (m/s)",
    ("own", "accel"): "the ego's acceleration (m/s²)",
    ("own", "yaw_rate"): "the ego's yaw rate (rad/s)",
    ("derived", "arc_gap"): "gap to that vehicle along its trail (arc length) (m)",
    ("derived", "desired_gap"): "the spacing policy's desired gap to it (m)",
    ("derived", "spacing_error"): "arc_gap − desired_gap (m)",
    ("derived", "speed"): "its latest speed (m/s)",
    ("derived", "valid"): "1 when that target is heard (leader: and is not a pred_m slot)",
    ("path", "cross_track"): "the trail's lateral offset from the ego (+ = trail to the "
    "ego's left), on the nearest heard predecessor's trail (m)",
    ("path", "heading_error"): "the trail's heading there minus the ego's, wrapped (rad)",
    ("path", "la0_x"): "trail point 0.5 s (at least 0.5 m) ahead, x (ego frame) (m)",
    ("path", "la0_y"): "trail point 0.5 s (at least 0.5 m) ahead, y (ego frame) (m)",
    ("path", "la1_x"): "trail point 1 s (at least 1 m) ahead, x (ego frame) (m)",
    ("path", "la1_y"): "trail point 1 s (at least 1 m) ahead, y (ego frame) (m)",
    ("path", "la2_x"): "trail point 2 s (at least 2 m) ahead, x (ego frame) (m)",
    ("path", "la2_y"): "trail point 2 s (at least 2 m) ahead, y (ego frame) (m)",
    ("path", "valid"): "1 when a predecessor's trail is known",
}

SCENARIOS = ("paper", "track", "emergency-braking")


def _num(x: float) -> str:
    if math.isinf(x):
        return "−∞" if x < 0 else "∞"
    if abs(x - math.pi) < 1e-6:
        return "π"
    if abs(x + math.pi) < 1e-6:
        return "−π"
    if abs(x - math.pi / 2) < 1e-6:
        return "π/2"
    if abs(x + math.pi / 2) < 1e-6:
        return "−π/2"
    return f"{x:g}".replace("-", "−")


def _doc(block: str, feature: str) -> str:
    try:
        return FEATURE_DOCS[(block, feature)]
    except KeyError:
        raise ValueError(
            f"docs/hooks/generated.py: observation feature {block}.{feature} has no "
            "description in FEATURE_DOCS"
        ) from None


def _layout_rows(layout: Any) -> list[tuple[int, str, str, str]]:
    """(index, slot, feature, block) for every value of the layout, in order."""
    from openconvoy.core import observation as ob

    rows: list[tuple[int, str, str, str]] = []
    for slot in layout.slots:
        for j in range(layout.k):
            for i, f in enumerate(ob.STATE_FEATURES):
                idx = layout.slot_offset(slot) + j * len(ob.STATE_FEATURES) + i
                rows.append((idx, f"{slot}[{j}]", f, "state"))
    for i, f in enumerate(ob.OWN_FEATURES):
        rows.append((layout.own_offset + i, "own", f, "own"))
    for target in layout.targets:
        for i, f in enumerate(ob.DERIVED_FEATURES):
            rows.append((layout.target_offset(target) + i, f"{target} (target)", f, "derived"))
    for i, f in enumerate(ob.PATH_FEATURES):
        rows.append((layout.path_offset + i, "path", f, "path"))
    if [r[0] for r in rows] != list(range(layout.size)):
        raise ValueError("docs/hooks/generated.py: the layout's offsets are not contiguous")
    return rows


def _default_layout() -> Any:
    from openconvoy.envs import ConvoyEnv

    return ConvoyEnv("paper").member_config.layout


def observation_blocks() -> str:
    from openconvoy.core import observation as ob

    lay = _default_layout()
    n_state = len(ob.STATE_FEATURES)
    out = [
        f"Layout version {lay.version}, M = {lay.M} predecessors, k = {lay.k} states per "
        f"vehicle: **{lay.size} float32 values**.",
        "",
        "| block | indices | values | contents |",
        "|---|---|---|---|",
    ]
    for slot in lay.slots:
        o = lay.slot_offset(slot)
        out.append(
            f"| state slot `{slot}` | {o}–{o + lay.slot_size - 1} | {lay.k} × {n_state} "
            f"| the last {lay.k} states heard, newest first: "
            + ", ".join(f"`{f}`" for f in ob.STATE_FEATURES)
            + " |"
        )
    o = lay.own_offset
    out.append(
        f"| own state | {o}–{o + len(ob.OWN_FEATURES) - 1} | {len(ob.OWN_FEATURES)} | "
        + ", ".join(f"`{f}`" for f in ob.OWN_FEATURES)
        + " |"
    )
    for t in lay.targets:
        o = lay.target_offset(t)
        out.append(
            f"| target `{t}` | {o}–{o + len(ob.DERIVED_FEATURES) - 1} | "
            f"{len(ob.DERIVED_FEATURES)} | "
            + ", ".join(f"`{f}`" for f in ob.DERIVED_FEATURES)
            + " |"
        )
    o = lay.path_offset
    out.append(
        f"| path | {o}–{o + len(ob.PATH_FEATURES) - 1} | {len(ob.PATH_FEATURES)} | "
        + ", ".join(f"`{f}`" for f in ob.PATH_FEATURES)
        + " |"
    )
    out += [
        "",
        f"Size in general: (M + 2) · k · {n_state} + {len(ob.OWN_FEATURES)} + (M + 1) · "
        f"{len(ob.DERIVED_FEATURES)} + {len(ob.PATH_FEATURES)}.",
    ]
    return "\n".join(out)


def observation_features() -> str:
    out = ["| block | feature | meaning (unit) |", "|---|---|---|"]
    for (block, feature), text in FEATURE_DOCS.items():
        out.append(f"| {block} | `{feature}` | {text} |")
    return "\n".join(out)


def observation_index() -> str:
    lay = _default_layout()
    low, high = lay.bounds()
    out = ["| index | slot | feature | low | high |", "|---|---|---|---|---|"]
    for idx, slot, feature, block in _layout_rows(lay):
        _doc(block, feature)
        out.append(
            f"| {idx} | {slot} | `{feature}` | {_num(float(low[idx]))} | {_num(float(high[idx]))} |"
        )
    return "\n".join(out)


def action() -> str:
    from openconvoy.envs import ConvoyEnv

    out = [
        "| scenario | vehicles (leader first) | agents | `action[0]`: speed setpoint [m/s] "
        "| `action[1]`: heading change [rad] | tick [s] | episode [s] |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in SCENARIOS:
        env = ConvoyEnv(name)
        agent = env.possible_agents[0]
        space = env.action_space(agent)
        for a in env.possible_agents:
            other = env.action_space(a)
            if not (other.low == space.low).all() or not (other.high == space.high).all():
                raise ValueError(f"{name}: agents' action spaces differ; extend the table")
        lo, hi = space.low, space.high
        out.append(
            f"| `{name}` | {', '.join(f'`{p.name}`' for p in env.presets)} "
            f"| {', '.join(f'`{a}`' for a in env.possible_agents)} "
            f"| {_num(float(lo[0]))} … {_num(float(hi[0]))} "
            f"| {_num(float(lo[1]))} … {_num(float(hi[1]))} "
            f"| {env.dt:g} | {env.max_time_s:.1f} |"
        )
    return "\n".join(out)


def reward() -> str:
    from openconvoy.envs.reward import RewardConfig

    out = ["| `RewardConfig` field | default |", "|---|---|"]
    for f in dataclasses.fields(RewardConfig):
        out.append(f"| `{f.name}` | {f.default} |")
    return "\n".join(out)


def info_keys() -> str:
    from openconvoy.envs.convoy_env import INFO_KEYS

    return ", ".join(f"`{k}`" for k in INFO_KEYS)


def environments() -> str:
    import gymnasium

    import openconvoy.envs  # noqa: F401  (registers the Gymnasium ids)
    from openconvoy.envs import SINGLE_AGENT_ID, ConvoyEnv

    paper = ConvoyEnv("paper")
    agent = paper.possible_agents[0]
    single = gymnasium.make(SINGLE_AGENT_ID)
    lay = paper.member_config.layout
    rows = [
        "| environment | API | observation | action | reward |",
        "|---|---|---|---|---|",
        f"| `ConvoyEnv(scenario)` | PettingZoo `ParallelEnv` (`.aec()` for AEC); agents "
        f"`follower_1` … | `Box({paper.observation_space(agent).shape[0]},)` per agent "
        f"| `Box({paper.action_space(agent).shape[0]},)` per agent | per agent |",
        f'| `gymnasium.make("{SINGLE_AGENT_ID}")` | Gymnasium `Env`: one learner '
        f"(`follower_1`), the others run a policy | `Box({single.observation_space.shape[0]},)` "
        f"| `Box({single.action_space.shape[0]},)` | the learner's |",
        f"| `VectorConvoyEnv(B, scenario)` | B convoys batched (numba) | `(B, N−1, {lay.size})` "
        "| `(B, N−1, 2)` | `(B, N−1)` |",
        '| `TrafficConvoyEnv` (`ConvoyEnv("highway-…")`) | as `ConvoyEnv` | as `ConvoyEnv` '
        "| as `ConvoyEnv` | as `ConvoyEnv` |",
    ]
    single.close()
    try:  # TrafficConvoyEnv needs the traffic extra; the row above says it keeps the spaces
        from openconvoy.envs.traffic.env import TrafficConvoyEnv
    except ModuleNotFoundError:
        pass
    else:
        if "_spaces" in TrafficConvoyEnv.__dict__:
            raise ValueError("TrafficConvoyEnv defines its own spaces: update this table")
    return "\n".join(rows)


def _toml_comments(doc: str) -> dict[tuple[str, str], str]:
    """``(section, key) -> comment`` from the commented TOML example in a module docstring."""
    out: dict[tuple[str, str], str] = {}
    section = ""
    for line in doc.splitlines():
        head = re.match(r"^\[(\w+)\]", line)
        if head:
            section = head.group(1)
            continue
        item = re.match(r"^(\w+)\s*=\s*(.*?)\s*#\s*(.+)$", line)
        if item and section:
            example, comment = item.group(2), item.group(3).strip()
            if comment.startswith("or "):  # "auth = "required"  # or "off"": say both
                comment = f"`{example}` {comment}"
            out[(section, item.group(1))] = comment
    return out


def _allowed(annotation: Any) -> str:
    from typing import get_args, get_origin

    from openconvoy.core.config import Range

    if get_origin(annotation) is tuple:
        parts = [_allowed(a) for a in get_args(annotation)]
        return "; ".join(p for p in parts if p)
    for meta in getattr(annotation, "__metadata__", ()):
        if isinstance(meta, Range):
            integer = int in get_args(annotation) or getattr(annotation, "__origin__", None) is int
            return meta.describe("integer" if integer else "number")
    return ""


def _type_name(annotation: Any) -> str:
    from typing import get_args, get_origin

    origin = get_origin(annotation)
    if origin is tuple:
        args = [a for a in get_args(annotation) if a is not Ellipsis]
        return "list of " + (
            _type_name(args[0]) + "s" if len(set(map(str, args))) == 1 else "numbers"
        )
    if getattr(annotation, "__metadata__", None):
        return _type_name(get_args(annotation)[0])
    names = {str: "string", int: "integer", float: "number", bool: "boolean"}
    if annotation in names:
        return names[annotation]
    args = [a for a in get_args(annotation) if a is not type(None)]
    if args:
        return " or ".join(_type_name(a) for a in args)
    return getattr(annotation, "__name__", str(annotation))


def convoy_file() -> str:
    import typing

    import openconvoy.convoy as cv

    comments = _toml_comments(cv.__doc__ or "")
    out = []
    for section, cls in (
        ("convoy", cv.ConvoyConfig),
        ("v2v", cv.V2VConfig),
        ("safety", cv.SafetyConfig),
        ("channel", cv.ChannelConfig),
    ):
        hints = typing.get_type_hints(cls, include_extras=True)
        out += [
            f"**`[{section}]`**",
            "",
            "| key | type | default | allowed | meaning |",
            "|---|---|---|---|---|",
        ]
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[f.name]):
                continue  # a nested section: its own table
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            if default == "" or default == ():
                shown = "(none)"
            elif isinstance(default, tuple):
                shown = "`" + repr(list(default)).replace("'", '"') + "`"
            elif isinstance(default, bool):
                shown = f"`{str(default).lower()}`"
            elif default is None:
                shown = "(see meaning)"
            else:
                shown = f"`{default!r}`".replace("'", '"')
            meaning = comments.get((section, f.name), "").replace("|", "\\|")
            out.append(
                f"| `{f.name}` | {_type_name(hints[f.name])} | {shown} | "
                f"{_allowed(hints[f.name])} | {meaning} |"
            )
        out.append("")
    return "\n".join(out)


TABLES: dict[str, Callable[[], str]] = {
    "convoy-file": convoy_file,
    "environments": environments,
    "observation-blocks": observation_blocks,
    "observation-features": observation_features,
    "observation-index": observation_index,
    "action": action,
    "reward": reward,
    "info-keys": info_keys,
}


def _text(name: str) -> str:
    if name not in TABLES:
        raise ValueError(f"unknown generated table {name!r} (known: {', '.join(TABLES)})")
    return TABLES[name]()


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    def block(match: re.Match[str]) -> str:
        indent = match.group(1)
        return "\n".join(
            indent + line if line else line for line in _text(match.group(2)).split("\n")
        )

    markdown = BLOCK.sub(block, markdown)
    return INLINE.sub(lambda m: _text(m.group(1)), markdown)
