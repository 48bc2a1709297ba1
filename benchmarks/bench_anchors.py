"""OpenConvoy beside the simulators users compare it with, measured in one run: ratios.

Each case runs in a fresh process pinned to one core (the first this script was given;
torch and numba held to one thread), alternating ours and the anchor's, and reports steps
per second and the process's peak memory. Ratios are ours ÷ anchor's, so the docs quote
ratios measured side by side rather than absolute figures from another machine. The rows
are issue 28's table:

- ``ConvoyEnv`` (the ``paper`` scenario, 3 vehicles, fixed actions) against SUMO through
  libsumo (a leader and two CACC followers on a straight road, ``--step-length 0.05``, each
  vehicle's speed and position read every step: what a controller needs), and
  ``VectorConvoyEnv`` at B = 1 against it.
- ``VectorConvoyEnv`` (PER 0.2, fixed actions) at B convoys against VMAS
  ``simple_spread`` (3 agents, CPU, one thread) at B environments, with both peak
  memories; and against libsumo running B convoys in one simulation.
- Long platoons, vehicle-steps/s against libsumo with 1 + n vehicles: all-predecessors
  with loss drawn on every pair and on the kept links only, and ``lookahead:1``
  (``--convoy-env-long``: ``ConvoyEnv`` too, minutes); ``ConvoyEnv`` 1 + ``--long``
  construction + reset time and peak memory.
- The largest B on ``--cores`` cores (threads) against one core, and whether the two
  runs' observations after 10 random ticks are identical.

Every case reports steps per wall-clock second and per CPU-second of its process; the
table prints both ratios. On a machine shared with other work the CPU-second ratio is the
one to read: the wall clock counts the time a case waited for a core. For the multi-core
case it is the work two threads do per CPU-second against one's (times the cores: the
speed-up idle cores would give, as far as the threads do not contend for memory bandwidth
or a shared cache).

A batched case's peak memory depends on how far its trails' rings widened (``rings`` in
the table: breadcrumbs a ring holds at the end), hence on how many ticks the timed run
managed; ``bench_vector_memory.py`` compares memory after a fixed number of ticks.

The anchors are optional installs (``pip install eclipse-sumo libsumo vmas``); a missing one
is reported and its ratios left out. The machine's cache sizes are printed with the table.

    python benchmarks/bench_anchors.py [--seconds 2] [--batches 1,64,1024,4096,16384]
        [--match "ConvoyEnv paper"] [--repeats 3]
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


def _timed(step: Any, seconds: float) -> tuple[int, float, float]:
    """Call ``step()`` for about ``seconds`` (at least once); (calls, seconds taken, CPU
    seconds of the process: all its threads)."""
    n, group, start, cpu = 0, 1, time.perf_counter(), time.process_time()
    while True:
        for _ in range(group):
            step()
        n += group
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return n, elapsed, time.process_time() - cpu
        group = min(group * 2, 20)  # a slow step is timed call by call


def _rates(steps: float, vehicles: int, s: float, cpu: float) -> dict[str, float]:
    """Env-steps and vehicle-steps per second and per CPU-second (a core shared with
    other work lowers the first, not the second)."""
    return {"steps_per_s": steps / s, "vehicle_steps_per_s": steps * vehicles / s,
            "steps_per_cpu_s": steps / cpu, "vehicle_steps_per_cpu_s": steps * vehicles / cpu}  # fmt: skip


def case_convoy_env(seconds: float, followers: int | None = None) -> dict[str, float]:
    import numpy as np

    from openconvoy.envs import ConvoyEnv

    _pin(1)
    env = ConvoyEnv("paper", n_followers=followers, max_time_s=1e5)
    env.reset(seed=0)
    action = {a: np.array([2.0, 0.0], dtype=np.float32) for a in env.possible_agents}
    n, s, cpu = _timed(lambda: env.step(action), seconds)
    return {**_rates(n, len(action), s, cpu), "peak_mb": _peak_mb()}


def _pin(cores: int) -> None:
    """Run this process on the first ``cores`` of the cores it was given (one-thread
    cases on one core, the multi-core case on several)."""
    allowed = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, allowed[: max(1, cores)])


def case_vector_env(
    seconds: float,
    batch: int,
    followers: int = 2,
    threads: int = 1,
    preset: str | None = None,
    link_counters: str = "kept",
) -> dict[str, Any]:
    """``VectorConvoyEnv`` with fixed actions (PER 0.2), on ``threads`` cores; ``preset``:
    a policy preset's member config (its topology), else the default (all-predecessors);
    ``link_counters``: the env's (``kept`` by default). ``digest``: of the observations
    after 10 ticks of random actions (the same whatever the thread count);
    ``steps_per_cpu_s``: steps per CPU-second of the process (all its threads), which
    a core shared with other work does not lower as it does the wall-clock rate."""
    import hashlib

    import numpy as np

    from openconvoy.envs import VectorConvoyEnv
    from openconvoy.policies.spec import load_policy

    _pin(threads)
    mc = load_policy(preset).member_config if preset else None
    env = VectorConvoyEnv(batch, "paper", n_followers=followers, max_time_s=1e5,
                          member_config=mc, loss=0.2, link_counters=link_counters,
                          threads=threads)  # fmt: skip
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(10):  # also compiles / loads the kernels outside the timing
        act = (rng.random((batch, followers, 2)) * [3.0, 0.1]).astype(np.float32)
        obs = env.step(act)[0]
    digest = hashlib.sha256(obs.tobytes()).hexdigest()[:16]
    action = np.tile(np.array([2.0, 0.0], dtype=np.float32), (batch, followers, 1))
    n, s, cpu = _timed(lambda: env.step(action), seconds)
    env.close()
    return {**_rates(n * batch, followers, s, cpu), "peak_mb": _peak_mb(), "digest": digest,
            "threads": env.threads, "window": env.rx.window}  # fmt: skip


def case_convoy_env_construct(followers: int) -> dict[str, float]:
    from openconvoy.envs import ConvoyEnv

    _pin(1)
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

    _pin(1)
    torch.set_num_threads(1)
    env = vmas.make_env("simple_spread", num_envs=batch, device="cpu", continuous_actions=True,
                        seed=0, n_agents=3)  # fmt: skip
    actions = [torch.zeros(batch, 2) for _ in env.agents]
    env.step(actions)
    n, s, cpu = _timed(lambda: env.step(actions), seconds)
    return {**_rates(n * batch, 3, s, cpu), "peak_mb": _peak_mb()}


def case_sumo(seconds: float, convoys: int, followers: int = 2) -> dict[str, float]:
    """``convoys`` convoys of a leader and ``followers`` CACC followers, each on its own
    straight road, one SUMO simulation; every vehicle's speed and position read per step."""
    import libsumo

    _pin(1)
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

            n, s, cpu = _timed(step, seconds)
        finally:
            libsumo.close()
    return {**_rates(n * convoys, followers + 1, s, cpu), "peak_mb": _peak_mb()}


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


def _median_run(runs: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """The run of median ``key`` among ``runs`` (the lower one of an even count)."""
    ranked = sorted(runs, key=lambda r: r.get(key, 0.0))
    return ranked[(len(ranked) - 1) // 2]


def _cases(args: argparse.Namespace) -> list[tuple[str, Any, Any, str]]:
    """The issue-28 table: (case, ours, anchor, key), each side a zero-argument call run
    in a fresh process."""
    sec, big = args.seconds, max(args.batches)

    def fresh(fn: Any, *a: Any) -> Any:
        return lambda: _in_fresh_process(fn, sec, *a)

    out = [
        ("ConvoyEnv paper vs libsumo CACC 1+2 with reads", fresh(case_convoy_env),
         fresh(case_sumo, 1), "steps_per_s"),
        ("VectorConvoyEnv B=1 vs ConvoyEnv paper", fresh(case_vector_env, 1),
         fresh(case_convoy_env), "steps_per_s"),
    ]  # fmt: skip
    for b in args.batches:
        out.append((f"VectorConvoyEnv B={b} vs VMAS simple_spread (one thread)",
                    fresh(case_vector_env, b), fresh(case_vmas, b), "steps_per_s"))  # fmt: skip
    out.append((f"VectorConvoyEnv B={args.sumo_batch} vs libsumo {args.sumo_batch} convoys "
                "in one simulation", fresh(case_vector_env, args.sumo_batch),
                fresh(case_sumo, args.sumo_batch), "steps_per_s"))  # fmt: skip
    for n in args.platoons:
        sumo = fresh(case_sumo, 1, n)
        out.append((f"VectorConvoyEnv 1+{n} all-predecessors, loss on all pairs vs libsumo",
                    fresh(case_vector_env, 1, n, 1, None, "all"), sumo,
                    "vehicle_steps_per_s"))  # fmt: skip
        out.append((f"VectorConvoyEnv 1+{n} all-predecessors, loss on kept links vs libsumo",
                    fresh(case_vector_env, 1, n, 1, None, "kept"), sumo,
                    "vehicle_steps_per_s"))  # fmt: skip
        out.append((f"VectorConvoyEnv 1+{n} lookahead:1, loss on kept links vs libsumo",
                    fresh(case_vector_env, 1, n, 1, "cacc-lookahead1", "kept"), sumo,
                    "vehicle_steps_per_s"))  # fmt: skip
    if args.convoy_env_long:
        out.append((f"ConvoyEnv 1+{args.long} all-predecessors vs libsumo 1+{args.long}",
                    fresh(case_convoy_env, args.long), fresh(case_sumo, 1, args.long),
                    "vehicle_steps_per_s"))  # fmt: skip
    out.append((f"VectorConvoyEnv B={big}: {args.cores} cores vs 1 core",
                fresh(case_vector_env, big, 2, args.cores), fresh(case_vector_env, big),
                "steps_per_s"))  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="timing per case (s)")
    ap.add_argument(
        "--batches", default="1,64,1024,4096,16384", help="B values for the batched cases"
    )
    ap.add_argument("--sumo-batch", type=int, default=1024, help="B against libsumo")
    ap.add_argument("--platoons", default="10,100,300,1000", help="long-platoon followers")
    ap.add_argument("--long", type=int, default=1000, help="followers of ConvoyEnv's long case")
    ap.add_argument("--convoy-env-long", action="store_true",
                    help="also step ConvoyEnv with --long followers (minutes)")  # fmt: skip
    ap.add_argument("--cores", type=int, default=2, help="cores of the multi-core case")
    ap.add_argument("--match", default="", help="only the cases whose name contains this")
    ap.add_argument("--repeats", type=int, default=1,
                    help="times each case runs, ours and the anchor alternating; the median "
                    "of each side")  # fmt: skip
    args = ap.parse_args()
    args.batches = [int(b) for b in args.batches.split(",")]
    args.platoons = [int(n) for n in args.platoons.split(",") if n]
    rows: list[dict[str, Any]] = []
    for case, ours_fn, anchor_fn, key in _cases(args):
        if args.match not in case:
            continue
        runs = [(ours_fn(), anchor_fn()) for _ in range(max(1, args.repeats))]  # alternating
        ours, anchor = (
            _median_run([o for o, _ in runs], key),
            _median_run([a for _, a in runs], key),
        )
        cpu_key = key.replace("_per_s", "_per_cpu_s")
        rows.append({"case": case, "ours": ours, "anchor": anchor, "key": key,
                     "ratio": _ratio(ours, anchor, key),
                     "ratio_cpu": _ratio(ours, anchor, cpu_key)})  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    long_case = f"ConvoyEnv 1+{args.long}: construct, reset, peak memory"
    if args.match in long_case:
        long_build = _in_fresh_process(case_convoy_env_construct, args.long)
        rows.append({"case": long_case, "ours": long_build})
        print(json.dumps(rows[-1]), flush=True)
    print()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"caches {cache_sizes()}, load {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"{'case':<78}{'ours':>13}{'anchor':>13}{'ratio':>8}{'per CPU-s':>10}{'MB ours':>9}"
          f"{'anchor':>8}")  # fmt: skip
    for r in rows:
        ours, anchor = r["ours"], r.get("anchor", {})
        if "construct_s" in ours:
            print(
                f"{r['case']:<78}{ours['construct_s']:>10.2f} s + {ours['reset_s']:.2f} s, "
                f"{ours['peak_mb']:.0f} MB"
            )
            continue
        ratio = r["ratio"] if r["ratio"] is not None else "-"
        ratio_cpu = r["ratio_cpu"] if r["ratio_cpu"] is not None else "-"
        same = ""
        if "digest" in ours and "digest" in anchor:
            same = "  identical" if ours["digest"] == anchor["digest"] else "  DIFFERENT"
        if "window" in ours:  # the trails' rings at the end: the peak memory depends on it
            same += f"  rings {ours['window']}"
        print(f"{r['case']:<78}{_cell(ours, r['key'])}{_cell(anchor, r['key'])}{ratio:>8}"
              f"{ratio_cpu:>10}{_mb(ours)}{_mb(anchor)}{same}")  # fmt: skip


def _mb(result: dict[str, Any]) -> str:
    return f"{result['peak_mb']:>8.0f}" if "peak_mb" in result else f"{'-':>8}"


def _cell(result: dict[str, Any], key: str) -> str:
    """A case's figure for the table, or the start of its error."""
    if key in result:
        return f"{result[key]:>13,.0f}"
    return f"{result.get('error', '-')[:12]:>13}"


if __name__ == "__main__":
    sys.exit(main())
