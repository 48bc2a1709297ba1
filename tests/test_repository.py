"""What a new user finds in a clone (issue 26): a short README that is not a development
log, whose links and install lines work; the LICENSE, CITATION.cff and CHANGELOG.md."""

from __future__ import annotations

import re
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")

DEV_LOG = re.compile(
    r"load average|\bload \d|\bround \d|\brounds?\b of development|\bissue \d+|#\d{2,}|"
    r"DESIGN\.md|\.\./shared|\bD\d{2}\b",
    re.IGNORECASE,
)
"""What a development log leaves in a README: load averages, rounds, internal issue and
decision numbers, the design file and data outside the repository."""


def test_the_readme_is_short_and_no_development_log() -> None:
    lines = README.splitlines()
    assert len(lines) <= 250, len(lines)
    found = [f"{n}: {ln}" for n, ln in enumerate(lines, 1) if DEV_LOG.search(ln)]
    assert not found, "\n".join(found)
    cells = [c.strip() for ln in lines if ln.startswith("|") for c in ln.strip("|").split("|")]
    assert max(map(len, cells), default=0) <= 120  # a table, not 600-character paragraphs


def test_the_pattern_catches_a_development_log() -> None:
    for line in (
        "measured at load average 7-12 on two cores",
        "fixed in round 4 (issue 17)",
        "see DESIGN.md, D61",
        "the data in ../shared/sitl",
    ):
        assert DEV_LOG.search(line), line


def test_every_readme_link_to_a_file_resolves() -> None:
    targets = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README)
    local = [t for t in targets if not t.startswith(("http://", "https://"))]
    assert local, "the README links to the documentation"
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, missing
    assert README.lstrip().splitlines()[0].startswith("# ")
    assert "(docs/cut-in.gif)" in README.split("\n## ")[0]  # the GIF at the top


def test_every_install_line_names_extras_that_exist() -> None:
    extras = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    )
    named = re.findall(r"pip install -e '\.\[([^\]]+)\]'", README)
    assert "traffic" in {e for group in named for e in group.split(",")}
    for group in named:
        assert set(group.split(",")) <= extras, group
    assert "pip install -e .  " in README or "pip install -e . " in README


def test_license_citation_and_changelog_are_in_the_repository() -> None:
    assert "MIT License" in (ROOT / "LICENSE").read_text(encoding="utf-8")
    cff = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert "cff-version: 1.2.0" in cff and "type: software" in cff
    assert re.search(r"preferred-citation:\n\s+type: article", cff)
    assert "OpenConvoy: Universal Platform for Real-World Testing" in cff
    assert all(name in cff for name in ("Burns", "Maghsoumi", "Fallah"))
    changelog = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert changelog.startswith("# Changelog") and "## [Unreleased]" in changelog
