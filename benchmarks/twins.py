"""Count the twins: batched code that restates a scalar rule (issue 21).

**Definition.** A *twin line* is a line of batched code that restates a rule the scalar
code also states: a line of a compiled function (decorated ``bare_inline``,
``bare_kernel`` or ``kernel``) of the batched modules, or of any function of the numpy
restatements and row code (``NUMPY_TWINS``), that computes — holds an arithmetic operator, a
comparison, a boolean operator, a conditional expression or a call of ``min``, ``max``,
``abs`` or a ``math``/``numpy`` function — outside an index (``a[i + 1]``) and outside a
loop's ``range(...)``. A kernel that only loops over the batch, loads and stores array
elements and calls a rule written once (a plain float function in its home module,
compiled through ``envs.vector.jit.rules`` or called by its scalar class too) has no twin
line: the rule's lines live once, in its home module. A conservative measure: loop and
guard comparisons (``if link < 0``) count too.

Prints, for the batched modules (``TWIN_MODULES``: the numba kernels of ``envs.vector``,
``envs.traffic.jit`` and ``policies.batched_jit``, and the numpy restatements):

- ``modules``: all their lines, the issue's first measure (~4,450 when it was filed);
- ``compiled``: the lines of their compiled functions, with and without docstrings,
  comments and blank lines (the previous round's measure);
- ``twin lines``: the definition above, with how many functions hold any, how many of
  those name their scalar reference in their docstring (``Twin of ``X````-style, a
  double-backquoted dotted name) and how many are property-tested (imported by name
  into a test module that uses hypothesis, or citing ``tests/PATH.py::test_NAME``, a
  test decorated ``@given``, in their docstring);
- the rules compiled from their home modules (``rules(...)`` calls) that no scalar code
  calls (each should have one: otherwise it is a twin moved, not a rule shared).

``--list`` names each function holding twin lines: its twin lines, compiled lines, the
reference its docstring names (``-`` where none) and ``hyp`` where a hypothesis test names
it. Usage: ``python benchmarks/twins.py [--list]``.
"""

from __future__ import annotations

import ast
import io
import re
import sys
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "openconvoy"
NUMPY_TWINS = (
    "envs/traffic/idm.py",
    "envs/traffic/road.py",
    "policies/batched.py",
    "policies/classical_rows.py",
)
"""Modules whose every function is batched code: the traffic model's numpy form, the
classical policy's batch (its numpy form until issue 21) and rows (plain Python that
``policies.batched_jit`` compiles)."""
TWIN_MODULES = (
    *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "envs" / "vector").glob("*.py")),
    "envs/traffic/jit.py",
    *NUMPY_TWINS,
    "policies/batched_jit.py",
)
COMPILED = {"bare_inline", "bare_kernel", "kernel"}
_REFERENCE = re.compile(r"``((?:core|envs|comms|policies)?\.?[A-Z_a-z][\w.]*\.\w+)``")
_CASTS = {"float64", "float32", "int64", "int32", "float", "int", "bool", "range", "len"}
_MATH = {"math", "np", "numpy"}


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


def _computes(node: ast.AST) -> bool:
    """``node`` itself computes (an operator, comparison, or a math call)."""
    if isinstance(node, ast.BinOp | ast.UnaryOp | ast.Compare | ast.BoolOp | ast.IfExp):
        return not (isinstance(node, ast.UnaryOp) and isinstance(node.operand, ast.Constant))
    if isinstance(node, ast.AugAssign):
        return True
    if isinstance(node, ast.Call):
        f = node.func
        if isinstance(f, ast.Name):
            return f.id in {"min", "max", "abs"}
        if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name):
            return f.value.id in _MATH and f.attr not in _CASTS
    return False


def twin_lines(fn: ast.FunctionDef) -> set[int]:
    """The lines of ``fn`` that compute (the module docstring's definition)."""
    lines: set[int] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Subscript):
            visit(node.value)  # the index is addressing, not the rule
            return
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id in {"range", "prefetch"}
        ):
            return
        if isinstance(node, ast.FunctionDef | ast.Expr) and node is not fn:
            if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
                return  # a docstring
        if _computes(node):
            lines.add(node.lineno)
        for child in ast.iter_child_nodes(node):
            if child in getattr(node, "decorator_list", ()) or isinstance(child, ast.arguments):
                continue
            visit(child)

    visit(fn)
    return lines


def functions(path: Path, every: bool) -> list[tuple[str, int, int, int, str, bool]]:
    """``(name, compiled lines, code lines, twin lines, reference, cites a property
    test)`` of each compiled function in ``path`` (each function where ``every``)."""
    out = []
    source = path.read_text()
    code = _code_lines(source)
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.FunctionDef):
            continue
        compiled = bool({ast.unparse(d) for d in node.decorator_list} & COMPILED)
        if not (compiled or every):
            continue
        first = min([d.lineno for d in node.decorator_list] + [node.lineno])
        assert node.end_lineno is not None
        found = _REFERENCE.search(ast.get_docstring(node) or "")
        span = range(first, node.end_lineno + 1)
        n_code = sum(1 for k in span if k in code) if compiled else 0
        n_twin = len(twin_lines(node))
        ref = found[1] if found else "-"
        cited = cites_a_property_test(ast.get_docstring(node) or "")
        out.append((node.name, len(span) if compiled else 0, n_code, n_twin, ref, cited))
    return out


def hypothesis_tests() -> str:
    """The text of the test modules that use hypothesis."""
    texts = [p.read_text() for p in sorted((REPO / "tests").rglob("test_*.py"))]
    return "\n".join(t for t in texts if "from hypothesis" in t)


_CITED = re.compile(r"(tests/[\w/]+\.py)::(test_\w+)")


def cites_a_property_test(doc: str) -> bool:
    """``doc`` names a test as ``tests/PATH.py::test_NAME`` that exists and is a
    hypothesis test (decorated ``@given``)."""
    for path, test in _CITED.findall(doc):
        file = REPO / path
        if not file.exists():
            continue
        tree = ast.parse(file.read_text())
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name == test:
                calls = [d.func for d in node.decorator_list if isinstance(d, ast.Call)]
                if any(getattr(f, "id", "") == "given" for f in calls):
                    return True
    return False


def property_tested(rel: str, name: str, tests: str) -> bool:
    """A hypothesis test module imports ``name`` from ``rel``'s module, or the module
    itself and reads ``alias.name``."""
    module = "openconvoy." + rel.removesuffix(".py").replace("/", ".")
    package, _, last = module.rpartition(".")
    if re.search(rf"from {re.escape(module)} import (?:\([^)]*?|[^\n]*?)\b{name}\b", tests):
        return True
    aliases = re.findall(
        rf"from {re.escape(package)} import (?:\([^)]*?|[^\n]*?)\b{last}(?: as (\w+))?", tests
    )
    return any(re.search(rf"\b{alias or last}\.{name}\b", tests) for alias in aliases)


EXTERNAL = {"envs/traffic/jit.py": "highway-env"}
"""Batched modules whose scalar reference is another project's code: the rules they share
with their numpy form have no scalar caller of ours (highway-env's is the reference)."""


def unshared_rules() -> tuple[list[str], list[str]]:
    """The rules the kernels compile from a home module (``rules(module, "name", ...)``)
    that no code outside the batched modules names besides its ``def`` (a twin moved, not a
    rule shared); and those of them registered by an ``EXTERNAL`` module (shared by its
    batched forms; the scalar reference is the other project's)."""
    twin_files = {ROOT / rel for rel in TWIN_MODULES}
    registered: list[tuple[str, str]] = []
    for rel in TWIN_MODULES:
        if not (ROOT / rel).exists():
            continue
        for node in ast.walk(ast.parse((ROOT / rel).read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "rules":
                registered += [(rel, a.value) for a in node.args[1:] if isinstance(a, ast.Constant)]
    scalar = "\n".join(p.read_text() for p in ROOT.rglob("*.py") if p not in twin_files)
    lonely = [(rel, n) for rel, n in registered if len(re.findall(rf"\b{n}\b", scalar)) < 2]
    return [n for rel, n in lonely if rel not in EXTERNAL], [
        f"{n} ({EXTERNAL[rel]})" for rel, n in lonely if rel in EXTERNAL
    ]


def main(argv: list[str]) -> None:
    """Print the counts (and with ``--list`` every function holding twin lines)."""
    modules = compiled = code = count = twins = holders = named = tested = 0
    tests = hypothesis_tests()
    for rel in TWIN_MODULES:
        path = ROOT / rel
        if not path.exists():  # an older tree, measured with this definition
            continue
        modules += len(path.read_text().splitlines())
        for name, lines, n_code, n_twin, ref, cited in functions(path, rel in NUMPY_TWINS):
            compiled += lines
            code += n_code
            count += lines > 0
            if not n_twin:
                continue
            twins += n_twin
            holders += 1
            named += ref != "-"
            hyp = cited or property_tested(rel, name, tests)
            tested += hyp
            if "--list" in argv:
                mark = "hyp" if hyp else "-"
                print(f"{rel}:{name:<20} {n_twin:4d} {lines:4d}  {mark:<3}  {ref}")
    print(f"modules: {modules} lines in {len(TWIN_MODULES)} modules")
    print(f"compiled: {compiled} lines ({code} of code) in {count} functions")
    print(
        f"twin lines: {twins} in {holders} functions, {named} naming a reference, "
        f"{tested} property-tested"
    )
    lonely, external = unshared_rules()
    print(f"rules compiled from a home module with no scalar caller: {', '.join(lonely) or 0}")
    print(
        f"rules shared by the batched forms of another project's model: {', '.join(external) or 0}"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
