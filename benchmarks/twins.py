"""Count the twins: batched code that restates a scalar rule (issue 21).

Prints two figures for the batched modules (``TWIN_MODULES``: the numba kernels of
``envs.vector``, ``envs.traffic.jit`` and ``policies.batched_jit``, and the numpy
restatements ``envs.traffic.idm``, ``envs.traffic.road`` and ``policies.batched``):

- ``modules``: all their lines, the issue's measure (~4,450 when it was filed);
- ``kernels``: the lines of their compiled functions (decorated ``bare_inline``,
  ``bare_kernel`` or ``kernel``), the code that computes a rule a second time; a rule
  compiled from its home module (``jit.rules``) is no line here.

``--list`` names each compiled function, its length and the scalar reference its
docstring names (``-`` where it names none). Usage: ``python benchmarks/twins.py [--list]``.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "openconvoy"
TWIN_MODULES = (
    *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "envs" / "vector").glob("*.py")),
    "envs/traffic/jit.py",
    "envs/traffic/idm.py",
    "envs/traffic/road.py",
    "policies/batched.py",
    "policies/batched_jit.py",
)
COMPILED = {"bare_inline", "bare_kernel", "kernel"}
_REFERENCE = re.compile(r"``((?:core|envs|comms|policies)?\.?[A-Z_a-z][\w.]*\.\w+)``")


def compiled_functions(path: Path) -> list[tuple[str, int, str]]:
    """``(name, lines, reference)`` of each compiled function in ``path``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.FunctionDef):
            continue
        decorators = {ast.unparse(d) for d in node.decorator_list}
        if decorators & COMPILED:
            first = min([d.lineno for d in node.decorator_list] + [node.lineno])
            assert node.end_lineno is not None
            found = _REFERENCE.search(ast.get_docstring(node) or "")
            out.append((node.name, node.end_lineno - first + 1, found[1] if found else "-"))
    return out


def main(argv: list[str]) -> None:
    """Print the counts (and with ``--list`` every compiled function)."""
    modules = kernels = named = count = 0
    for rel in TWIN_MODULES:
        path = ROOT / rel
        modules += len(path.read_text().splitlines())
        for name, lines, ref in compiled_functions(path):
            kernels += lines
            count += 1
            named += ref != "-"
            if "--list" in argv:
                print(f"{rel}:{name:<20} {lines:4d}  {ref}")
    print(f"twin modules: {modules} lines in {len(TWIN_MODULES)} modules")
    print(f"compiled twins: {kernels} lines in {count} functions, {named} naming a reference")


if __name__ == "__main__":
    main(sys.argv[1:])
