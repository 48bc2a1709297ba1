"""Without the traffic extra the core works and highway scenarios fail in one clear line."""

from __future__ import annotations

import subprocess
import sys

BLOCK = "import sys; sys.modules['highway_env'] = None; "


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code], capture_output=True, text=True, timeout=120
    )


def test_core_env_runs_without_highway_env() -> None:
    r = _run(
        "from openconvoy.envs import ConvoyEnv; e = ConvoyEnv(); e.reset(seed=0); "
        "print('highway_env' in sys.modules and sys.modules['highway_env'] is not None)"
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"


def test_highway_scenario_without_the_extra_is_one_error_line() -> None:
    r = _run(
        "from openconvoy.cli import main; sys.exit(main(['sim', '--scenario', 'highway-cut-in', "
        "'--out', '/nonexistent/never-written', '--quiet']))"
    )
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "openconvoy: error: highway-* scenarios need highway-env: pip install 'openconvoy[traffic]'"
    ]
