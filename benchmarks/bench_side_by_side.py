"""This tree's speed beside another tree's (a baseline commit checked out with ``git
worktree add /tmp/base COMMIT``), alternating the two in one run so both see the same load.

Cases: ``bench_vector_env``'s paper scenario at B = 1,024 with fixed actions and with the
paper policy acting batched, and ``bench_env``'s ``ConvoyEnv`` (2 followers) with fixed
actions and closed loop, on its compiled backend (``single-``, what ``ConvoyEnv`` runs
where numba is installed) and on its Python backend (``python-``, what vehicles run). Each round runs every case once per tree, each in a fresh process
(``PYTHONPATH`` the tree; pinned to one core with ``--cpu``), after one untimed run per
case and tree that compiles or loads its kernels; the table gives per case the
median over rounds of each tree's rate per CPU-second of the process and the ratio
new / base. Prints the load average at start and end.

    python benchmarks/bench_side_by_side.py /tmp/base [--rounds 3] [--seconds 2] [--cpu 0] [--cases ...]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
_CASE = r"""
import json, sys, time
sys.path.insert(0, "benchmarks")
case, seconds = sys.argv[1], float(sys.argv[2])
if case.startswith("vector"):
    from bench_vector_env import bench_vector
    row = bench_vector(seconds=seconds, B=1024, vehicles=3, policy=case == "vector-policy")
    print(json.dumps(row["env_steps_per_cpu_s"]))
else:
    import bench_env
    backend = "python" if case.startswith("python") else "compiled"
    env, policies = bench_env._make(2, None, backend)
    pol = policies if case.endswith("-policy") else None
    bench_env._run(env, pol, 0.2, 10**9)
    t0 = time.process_time()
    steps, _ = bench_env._run(env, pol, seconds, 10**9)
    print(json.dumps(steps / (time.process_time() - t0)))
"""
CASES = (
    "vector-fixed",
    "vector-policy",
    "single-fixed",
    "single-policy",
    "python-fixed",
    "python-policy",
)


def _rate(tree: Path, case: str, seconds: float, cpu: int | None) -> float:
    """One case's env steps per CPU-second in a fresh process on ``tree``'s code."""
    cmd = [sys.executable, "-c", _CASE, case, str(seconds)]
    if cpu is not None:
        cmd = ["taskset", "-c", str(cpu), *cmd]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"{case} on {tree} failed:\n{out.stderr[-2000:]}")
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Alternate the trees and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", type=Path, help="the other tree (a git worktree)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--cpu", type=int, default=None, help="pin every run to this core")
    ap.add_argument("--cases", nargs="+", choices=CASES, default=CASES, help="cases to run")
    args = ap.parse_args()
    for tree in (args.base.resolve(), HERE):  # compile (or load) each tree's kernels first
        for case in args.cases:
            _rate(tree, case, 0.2, args.cpu)
    print(f"load average at start: {os.getloadavg()}")
    rates: dict[tuple[str, str], list[float]] = {}
    for r in range(args.rounds):
        for case in args.cases:
            for name, tree in (("base", args.base.resolve()), ("new", HERE)):
                rate = _rate(tree, case, args.seconds, args.cpu)
                rates.setdefault((case, name), []).append(rate)
                print(json.dumps({"round": r, "case": case, "tree": name, "per_cpu_s": rate}))
    print(f"load average at end: {os.getloadavg()}\n")
    print("| case | base env-steps/CPU-s | new | new / base |\n|---|---|---|---|")
    for case in args.cases:
        base = statistics.median(rates[(case, "base")])
        new = statistics.median(rates[(case, "new")])
        print(f"| {case} | {base:,.0f} | {new:,.0f} | {new / base:.3f} |")


if __name__ == "__main__":
    main()
