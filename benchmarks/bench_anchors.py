"""OpenConvoy beside the simulators users compare it with, measured in one run: ratios.

Each case runs in a fresh process on one core (``taskset`` is the caller's choice; torch and
numba are held to one thread), alternating ours and the anchor's, and reports steps per
second and the process's peak memory. Ratios are ours ÷ anchor's, so the docs quote ratios
measured side by side rather than absolute figures from another machine.

- ``ConvoyEnv`` (the ``paper`` scenario, 3 vehicles, fixed actions) against SUMO through
  libsumo (a leader and two CACC followers on a straight road, ``--step-length 0.05``, each
  vehicle's speed and position read every step: what a controller needs).
- ``VectorConvoyEnv`` at B convoys against VMAS ``simple_spread`` (3 agents, CPU, one
  thread) at B environments; and against libsumo running B convoys in one simulation.
- A 1,000-follower convoy: ``ConvoyEnv`` construction + reset time and peak memory;
  ``VectorConvoyEnv(1)`` vehicle-steps/s against libsumo with 1 + 1,000 vehicles.

The anchors are optional installs (``pip install eclipse-sumo libsumo vmas``); a missing one
is reported and its ratios left out. The machine's cache sizes are printed with the table.

    python benchmarks/bench_anchors.py [--seconds 2] [--batches 1,64,1024,4096,16384]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

DT = 0.05  # s: the control period of every case (20 Hz)


# --- cases (each runs in its own process) ------------------------------------------------


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(step: Any, seconds: float) -> tuple[int, float]:
    """Call ``step()`` for about ``seconds``; (calls, seconds taken)."""
    n, start = 0, time.perf_counter()
    while True:
        for _ in range(20):
            step()
        n += 20
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return n, elapsed


def case_convoy_env(seconds: float) -> dict[str, float]:
    import numpy as np

    from openconvoy.envs import ConvoyEnv

    env = ConvoyEnv("paper", max_time_s=1e6)
    env.reset(seed=0)
    action = {a: np.array([2.0, 0.0], dtype=np.float32) for a in env.possible_agents}
    n, s = _timed(lambda: env.step(action), seconds)
    return {"steps_per_s": n / s, "peak_mb": _peak_mb()}


def case_vector_env(seconds: float, batch: int, followers: int = 2) -> dict[str, float]:
    import numpy as np

    from openconvoy.envs import VectorConvoyEnv

    env = VectorConvoyEnv(batch, "paper", n_followers=followers, max_time_s=1e6)
    env.reset(seed=0)
    action = np.tile(np.array([2.0, 0.0], dtype=np.float32), (batch, followers, 1))
    env.step(action)  # compile / load the kernels outside the timing
    n, s = _timed(lambda: env.step(action), seconds)
    return {"steps_per_s": n * batch / s, "vehicle_steps_per_s": n * batch * followers / s,
            "peak_mb": _peak_mb()}  # fmt: skip


def case_convoy_env_construct(followers: int) -> dict[str, float]:
    from openconvoy.envs import ConvoyEnv

    start = time.perf_counter()
    env = ConvoyEnv("paper", n_followers=followers)
    built = time.perf_counter()
    env.reset(seed=0)
    return {
        "construct_s": built - start,
        "reset_s": time.perf_counter() - built,
        "peak_mb": _peak_mb(),
    }


def case_vmas(seconds: float, batch: int) -> dict[str, float]:
    import torch
    import vmas

    torch.set_num_threads(1)
    env = vmas.make_env("simple_spread", num_envs=batch, device="cpu", continuous_actions=True,
                        seed=0, n_agents=3)  # fmt: skip
    actions = [torch.zeros(batch, 2) for _ in env.agents]
    env.step(actions)
    n, s = _timed(lambda: env.step(actions), seconds)
    return {"steps_per_s": n * batch / s, "peak_mb": _peak_mb()}


def case_sumo(seconds: float, convoys: int, followers: int = 2) -> dict[str, float]:
    """``convoys`` convoys of a leader and ``followers`` CACC followers, each on its own
    straight road, one SUMO simulation; every vehicle's speed and position read per step."""
    import libsumo

    with tempfile.TemporaryDirectory(prefix="oc-sumo-") as tmp:
        net, routes = _sumo_files(Path(tmp), convoys, followers)
        libsumo.start(["sumo", "-n", str(net), "-r", str(routes), "--step-length", str(DT),
                       "--no-step-log", "--no-warnings", "--seed", "0"])  # fmt: skip
        try:
            libsumo.simulationStep()
            ids = list(libsumo.vehicle.getIDList())
            expected = convoys * (followers + 1)
            if len(ids) != expected:
                raise RuntimeError(f"SUMO inserted {len(ids)} of {expected} vehicles")

            def step() -> None:
                libsumo.simulationStep()
                for v in ids:
                    libsumo.vehicle.getSpeed(v)
                    libsumo.vehicle.getPosition(v)

            n, s = _timed(step, seconds)
        finally:
            libsumo.close()
    return {"steps_per_s": n * convoys / s, "vehicle_steps_per_s": n * len(ids) / s,
            "peak_mb": _peak_mb()}  # fmt: skip


def _sumo_files(tmp: Path, convoys: int, followers: int) -> tuple[Path, Path]:
    """A straight 100 km single-lane road per convoy (10 m apart) and the convoys on them:
    the leader (Krauss at 5 m/s) ahead of CACC followers 15 m apart."""
    from sumo import SUMO_HOME

    length = 100_000.0
    nodes = ["<nodes>"] + [
        f'<node id="a{c}" x="0" y="{10 * c}"/><node id="b{c}" x="{length}" y="{10 * c}"/>'
        for c in range(convoys)
    ] + ["</nodes>"]  # fmt: skip
    edges = ["<edges>"] + [
        f'<edge id="e{c}" from="a{c}" to="b{c}" numLanes="1" speed="30"/>' for c in range(convoys)
    ] + ["</edges>"]  # fmt: skip
    (tmp / "n.nod.xml").write_text("\n".join(nodes))
    (tmp / "e.edg.xml").write_text("\n".join(edges))
    net = tmp / "net.xml"
    subprocess.run(
        [str(Path(SUMO_HOME) / "bin" / "netconvert"), "-n", str(tmp / "n.nod.xml"),
         "-e", str(tmp / "e.edg.xml"), "-o", str(net), "--no-warnings"],
        check=True, capture_output=True,
    )  # fmt: skip
    lines = [
        "<routes>",
        '<vType id="lead" carFollowModel="Krauss" maxSpeed="5" length="0.8" minGap="0.5"/>',
        '<vType id="cacc" carFollowModel="CACC" maxSpeed="6" length="0.8" minGap="0.5"/>',
    ]
    gap = 15.0
    for c in range(convoys):
        lines.append(f'<route id="r{c}" edges="e{c}"/>')
        head = 10.0 + gap * followers
        lines.append(
            f'<vehicle id="c{c}_0" type="lead" route="r{c}" depart="0" departPos="{head}" departSpeed="0"/>'
        )
        for f in range(1, followers + 1):
            lines.append(
                f'<vehicle id="c{c}_{f}" type="cacc" route="r{c}" depart="0" '
                f'departPos="{head - gap * f}" departSpeed="0"/>'
            )
    lines.append("</routes>")
    routes = tmp / "routes.rou.xml"
    routes.write_text("\n".join(lines))
    return net, routes


# --- the driver --------------------------------------------------------------------------


def _in_fresh_process(fn: Any, *args: Any) -> dict[str, Any]:
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        try:
            return pool.submit(fn, *args).result()
        except Exception as exc:  # noqa: BLE001 - an anchor missing or failing is reported
            return {
                "error": f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            }


def cache_sizes() -> dict[str, str]:
    """The CPU's cache sizes as Linux reports them (``L1d``, ``L2``, ``L3``)."""
    out: dict[str, str] = {}
    base = Path("/sys/devices/system/cpu/cpu0/cache")
    for index in sorted(base.glob("index*")):
        try:
            level = (index / "level").read_text().strip()
            kind = (index / "type").read_text().strip()
            size = (index / "size").read_text().strip()
        except OSError:
            continue
        if kind != "Instruction":
            out[f"L{level}" + ("d" if kind == "Data" else "")] = size
    return out


def _ratio(ours: dict[str, Any], anchor: dict[str, Any], key: str = "steps_per_s") -> float | None:
    if key in ours and key in anchor and anchor[key] > 0:
        return round(ours[key] / anchor[key], 3)
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="timing per case (s)")
    ap.add_argument(
        "--batches", default="1,64,1024,4096,16384", help="B values for the batched cases"
    )
    ap.add_argument("--long", type=int, default=1000, help="followers of the long platoon")
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    rows: list[dict[str, Any]] = []

    def row(
        case: str, ours: dict[str, Any], anchor: dict[str, Any], key: str = "steps_per_s"
    ) -> None:
        rows.append(
            {"case": case, "ours": ours, "anchor": anchor, "ratio": _ratio(ours, anchor, key)}
        )
        print(json.dumps(rows[-1]), flush=True)

    row("ConvoyEnv paper vs libsumo CACC 1+2 with reads",
        _in_fresh_process(case_convoy_env, args.seconds), _in_fresh_process(case_sumo, args.seconds, 1))  # fmt: skip
    for b in batches:
        ours = _in_fresh_process(case_vector_env, args.seconds, b)
        row(f"VectorConvoyEnv B={b} vs VMAS simple_spread (one thread)", ours,
            _in_fresh_process(case_vmas, args.seconds, b))  # fmt: skip
    for b in [b for b in batches if b in (1024,)]:
        row(f"VectorConvoyEnv B={b} vs libsumo {b} convoys in one simulation",
            _in_fresh_process(case_vector_env, args.seconds, b), _in_fresh_process(case_sumo, args.seconds, b))  # fmt: skip
    row(f"VectorConvoyEnv 1+{args.long} vs libsumo 1+{args.long} (vehicle-steps/s)",
        _in_fresh_process(case_vector_env, args.seconds, 1, args.long),
        _in_fresh_process(case_sumo, args.seconds, 1, args.long), key="vehicle_steps_per_s")  # fmt: skip
    long_build = _in_fresh_process(case_convoy_env_construct, args.long)
    rows.append(
        {"case": f"ConvoyEnv 1+{args.long}: construct, reset, peak memory", "ours": long_build}
    )
    print(json.dumps(rows[-1]), flush=True)
    print()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"caches {cache_sizes()}, load {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"{'case':<72}{'ours':>14}{'anchor':>14}{'ratio':>8}")
    for r in rows:
        ours, anchor = r["ours"], r.get("anchor", {})
        if "construct_s" in ours:
            print(
                f"{r['case']:<72}{ours['construct_s']:>11.2f} s + {ours['reset_s']:.2f} s, "
                f"{ours['peak_mb']:.0f} MB"
            )
            continue
        key = "vehicle_steps_per_s" if "vehicle" in r["case"] else "steps_per_s"
        ratio = r["ratio"] if r["ratio"] is not None else "-"
        print(f"{r['case']:<72}{_cell(ours, key)}{_cell(anchor, key)}{ratio:>8}")


def _cell(result: dict[str, Any], key: str) -> str:
    """A case's figure for the table, or the start of its error."""
    if key in result:
        return f"{result[key]:>14,.0f}"
    return f"{result.get('error', '-')[:13]:>14}"


if __name__ == "__main__":
    sys.exit(main())
