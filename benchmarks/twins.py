"""Count the twins: batched code that restates a scalar rule (issue 21).

Prints two figures for the batched modules (``TWIN_MODULES``: the numba kernels of
``envs.vector``, ``envs.traffic.jit`` and ``policies.batched_jit``, and the numpy
restatements ``envs.traffic.idm``, ``envs.traffic.road`` and ``policies.batched``):

- ``modules``: all their lines, the issue's measure (~4,450 when it was filed);
- ``compiled twins``: the lines of their compiled functions (decorated ``bare_inline``,
  ``bare_kernel`` or ``kernel``), the code that computes a rule a second time, with and
  without docstrings, comments and blank lines; a rule compiled from its home module
  (``jit.rules``) is no line here.

``--list`` names each compiled function, its length and the scalar reference its
docstring names (``-`` where it names none). Usage: ``python benchmarks/twins.py [--list]``.
"""

from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
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


def _code_lines(source: str) -> set[int]:
    """The numbers of the lines of ``source`` holding code (not docstrings, comments or
    blank lines)."""
    lines: set[int] = set()
    skip = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT)
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in skip or tok.type == tokenize.ENDMARKER:
            continue
        if tok.type == tokenize.STRING and tok.line.lstrip().startswith(('"""', 'r"""')):
            continue
        lines.update(range(tok.start[0], tok.end[0] + 1))
    return lines


def compiled_functions(path: Path) -> list[tuple[str, int, int, str]]:
    """``(name, lines, code lines, reference)`` of each compiled function in ``path``."""
    out = []
    source = path.read_text()
    code = _code_lines(source)
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.FunctionDef):
            continue
        decorators = {ast.unparse(d) for d in node.decorator_list}
        if decorators & COMPILED:
            first = min([d.lineno for d in node.decorator_list] + [node.lineno])
            assert node.end_lineno is not None
            found = _REFERENCE.search(ast.get_docstring(node) or "")
            span = range(first, node.end_lineno + 1)
            n_code = sum(1 for k in span if k in code)
            out.append((node.name, len(span), n_code, found[1] if found else "-"))
    return out


def main(argv: list[str]) -> None:
    """Print the counts (and with ``--list`` every compiled function)."""
    modules = kernels = code = named = count = 0
    for rel in TWIN_MODULES:
        path = ROOT / rel
        modules += len(path.read_text().splitlines())
        for name, lines, n_code, ref in compiled_functions(path):
            kernels += lines
            code += n_code
            count += 1
            named += ref != "-"
            if "--list" in argv:
                print(f"{rel}:{name:<20} {lines:4d} {n_code:4d}  {ref}")
    print(f"twin modules: {modules} lines in {len(TWIN_MODULES)} modules")
    print(
        f"compiled twins: {kernels} lines ({code} of code) in {count} functions, "
        f"{named} naming a reference"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
