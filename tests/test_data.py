"""The suite is self-contained: no test, benchmark or package module reads outside the
repository (a clone has no ../shared), and every file in tests/data is accounted for in its
README, with the data kept small."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"

# A path built to a sibling of the repository: parents[...] / "shared", "../shared/...",
# or REPO_ROOT.parent / ...
OUTSIDE = re.compile(
    r"""(\.parents?\[\d\]\s*/\s*["']shared|["']\.\./shared|ROOT\.parent\s*/|\.parent\s*/\s*["']shared)"""
)


def test_no_source_reads_a_sibling_of_the_repository() -> None:
    offenders = []
    for folder in ("openconvoy", "tests", "benchmarks", "examples"):
        for path in (ROOT / folder).rglob("*.py"):
            if path == Path(__file__).resolve():
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if OUTSIDE.search(line):
                    offenders.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_the_pattern_catches_the_old_ways() -> None:
    for line in (
        'SHARED = Path(__file__).parents[3].parent / "shared"',
        'VECTORS = REPO_ROOT.parent / "shared" / "interop"',
        'CONVOY = Path(__file__).resolve().parents[2] / "shared" / "sitl"',
        'p = "../shared/sitl/x.jsonl.gz"',
    ):
        assert OUTSIDE.search(line), line
    assert not OUTSIDE.search('DATA = Path(__file__).resolve().parents[2] / "data"')


def test_every_data_file_is_described_and_the_data_stays_small() -> None:
    readme = (DATA / "README.md").read_text(encoding="utf-8")
    files = [p for p in DATA.rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    for path in files:
        rel = path.relative_to(DATA)
        top = rel.parts[0] if len(rel.parts) > 1 else rel.name
        # Each file, or the folder it is in, is named in the README's table.
        assert f"`{top}" in readme or rel.name in readme, rel
    assert sum(p.stat().st_size for p in files) < 8_000_000
