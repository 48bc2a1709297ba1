"""DESIGN.md's import rule, checked on the source (every import, lazy ones inside functions too).

Imports point one way: ``core`` imports nothing of ours; ``logs``, ``comms`` import ``core``;
``envs`` imports ``core``, ``comms``, ``logs``; ``policies`` import ``core`` only; ``experiments``
imports ``envs``, ``policies``, ``logs``; ``bridge`` imports ``core``, ``comms``, ``logs``,
``policies`` and the plant of ``envs``; ``train`` imports ``envs``, ``policies``, ``experiments``;
``cli.py`` and ``demo.py`` sit on top; ``testing`` (the fakes and parity helpers shipped
for tests) imports ``core``, ``comms``, ``policies``, ``bridge`` and the leaves, and nothing
imports it. ``bag.py`` (runs as ROS 2 bags) sits beside ``logs``.
``convoy.py`` (the convoy config shared by sim and deploy)
and ``outputs.py`` (output-path checks) are leaf modules beside ``logs``: they import ``core`` only.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "openconvoy"

LEAVES = {"core", "logs", "bag", "convoy", "outputs"}  # what any layer above the leaves may import
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "logs": {"core"},
    "bag": {"core", "logs"},
    "convoy": {"core"},
    "outputs": {"core"},
    "comms": {"core"},
    "policies": {"core"},
    "envs": LEAVES | {"comms"},
    "experiments": LEAVES | {"comms", "envs", "policies"},
    "bridge": LEAVES | {"comms", "policies", "envs"},
    "train": LEAVES | {"comms", "envs", "policies", "experiments"},
    "testing": LEAVES | {"comms", "policies", "bridge"},
}
# Module-level exceptions, each with its reason; anything else breaking the rule fails the test.
EXCEPTIONS: dict[tuple[str, str], str] = {
    # The single-agent Gymnasium env drives the other followers with a policy spec (lazily).
    ("openconvoy.envs.single_agent", "openconvoy.policies.spec"): "co-followers' policy",
    # The BSM tools (`bsm send`/`listen`) read the convoy file at the CLI edge.
    ("openconvoy.comms.cli", "openconvoy.convoy"): "CLI reads the convoy config",
    # ``read_log`` reads a ROS 2 bag through ``bag.read_bag`` (lazily), as it reads a CSV.
    ("openconvoy.logs", "openconvoy.bag"): "read_log reads bags too",
}
# bridge may import only these parts of envs: the plant, the vehicle presets, the leader scenarios.
BRIDGE_ENVS = {"openconvoy.envs.plant", "openconvoy.envs.vehicles", "openconvoy.envs.scenarios"}


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    module = _module(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                found.add(".".join(base + ([node.module] if node.module else [])))
            else:
                found.add(node.module or "")
    return {name for name in found if name.startswith("openconvoy.")}


def _layer(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test_every_layer_is_known() -> None:
    layers = {_layer(_module(p)) for p in SOURCES} - {"", "cli", "demo"}
    assert layers == set(ALLOWED), layers ^ set(ALLOWED)


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path: Path) -> None:
    module = _module(path)
    layer = _layer(module)
    if layer in ("", "cli", "demo"):
        return  # the top: imports what a subcommand needs
    wrong = []
    for target in sorted(_imports(path)):
        to = _layer(target)
        if to == layer or (module, target) in EXCEPTIONS:
            continue
        if to not in ALLOWED[layer]:
            wrong.append(target)
        elif layer == "bridge" and to == "envs" and target not in BRIDGE_ENVS:
            wrong.append(target)
    assert not wrong, f"{module} imports {wrong}, against DESIGN.md's import rule"


def _private_imports(path: Path) -> list[tuple[str, str]]:
    """``(module, name)`` of every ``from openconvoy.X import _name`` in ``path``."""
    module = _module(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom):
            continue
        source = node.module or ""
        if node.level:
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            source = ".".join(base + ([node.module] if node.module else []))
        if source.startswith("openconvoy"):
            found += [
                (source, a.name)
                for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")  # not __version__
            ]
    return found


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_takes_another_packages_private_name(path: Path) -> None:
    """A leading underscore is private to its package: modules of one package (say
    ``envs.vector``, whose kernels share helpers) may share such names, no one else."""
    package = _module(path).rpartition(".")[0] if path.name != "__init__.py" else _module(path)
    wrong = [
        f"{source}.{name}"
        for source, name in _private_imports(path)
        if source.rpartition(".")[0] != package and source != package
    ]
    assert not wrong, f"{_module(path)} imports private {wrong}"


def test_test_modules_have_unique_names() -> None:
    """The tests mirror the package tree, but their folders are not packages: pytest
    imports each test module by its file name, so two ``test_links.py`` in different
    folders stop the collection ("import file mismatch")."""
    tests = Path(__file__).resolve().parent
    seen: dict[str, Path] = {}
    clashes = []
    for path in sorted(tests.rglob("test_*.py")):
        if "data" in path.relative_to(tests).parts:
            continue
        if path.name in seen:
            clashes.append((seen[path.name], path))
        seen.setdefault(path.name, path)
    assert not clashes, clashes
