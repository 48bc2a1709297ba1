"""A minimal install (``pip install openconvoy``, no extras) runs ``sim``; every command that
needs an extra says which one in one line (exit 2) instead of a ModuleNotFoundError
traceback (issue 26 item 4). Each case runs the real CLI in a fresh interpreter in which
the extra's packages cannot be imported, as on a machine without them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from openconvoy.cli import EXTRAS, missing_extra
from tests.firmware_runs import unpack

REPO = Path(__file__).resolve().parents[1]

# Imports of these top-level packages fail in the child, as if they were not installed.
_RUN = """
import importlib.abc, sys
BLOCKED = set(sys.argv[1].split(","))
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None
sys.meta_path.insert(0, Block())
from openconvoy.cli import main
sys.exit(main(sys.argv[2:]))
"""


def run_without(packages: set[str], *argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _RUN, ",".join(sorted(packages)), *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
    )


def extra_packages(extra: str) -> set[str]:
    return {module for module, e in EXTRAS.items() if e == extra}


ALL_EXTRAS = set(EXTRAS)


def test_sim_runs_without_any_extra_and_says_why_there_are_no_plots(tmp_path: Path) -> None:
    out = tmp_path / "run"
    r = run_without(
        ALL_EXTRAS, "sim", "--duration", "5", "--quiet", "--out", str(out), cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["log.csv", "metrics.json", "run.toml"]
    notes = [ln for ln in r.stderr.splitlines() if "matplotlib is not installed" in ln]
    assert notes == [
        "openconvoy: note: no plots, matplotlib is not installed "
        "(pip install 'openconvoy[plots]'; --no-plots skips them)"
    ]
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "extra,argv",
    [
        ("vehicle", ["bsm", "decode", "0014"]),
        ("vehicle", ["keys", "init", "--convoy", "c.toml"]),
        ("vehicle", ["deploy", "--policy", "paper", "--vehicle-id", "0", "--convoy", "c.toml",
                     "--mavlink", "udpin:127.0.0.1:1", "--iface", "lo", "--log", "log"]),
        ("train", ["train", "--out", "t"]),
        ("train", ["tune", "--policy", "paper", "--trials", "1", "--out", "t.toml"]),
        ("plots", ["report", "{data}/vx-fixed-1", "--plots", "--out", "m.json"]),
    ],
)  # fmt: skip
def test_a_command_without_its_extra_names_the_extra_in_one_line(
    extra: str, argv: list[str], tmp_path: Path
) -> None:
    (tmp_path / "c.toml").write_text(
        '[convoy]\nname = "lab"\nvehicles = ["1/10", "1/6"]\norigin = [28.6, -81.2, 0.0]\n'
    )
    data = tmp_path / "data"
    unpack("vx-fixed-1", data)
    argv = [a.replace("{data}", str(data)) for a in argv]
    r = run_without(extra_packages(extra), *argv, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    errors = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and "Traceback" not in r.stderr, r.stderr
    assert errors[0].startswith(f"openconvoy {argv[0]}: error: this command needs the '{extra}'")
    assert f"pip install 'openconvoy[{extra}]'" in errors[0]


def test_other_missing_modules_are_bugs_not_extras() -> None:
    assert missing_extra(ModuleNotFoundError("x", name="openconvoy.nothing")) is None
    assert missing_extra(ModuleNotFoundError("x", name="yaml")) is None
    line = missing_extra(ModuleNotFoundError("x", name="stable_baselines3.common"))
    assert line is not None and "'train' extra" in line


def test_every_extra_named_exists_in_pyproject() -> None:
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert set(EXTRAS.values()) <= set(extras)
