"""VectorConvoyEnv's memory at large batches after a fixed number of ticks: a JSON line per
case, each in a fresh process on one core.

``bench_anchors.py`` reports each case's peak memory after a timed run, whose length (and
so how far the trails' rings have widened: ``vector.trail``) depends on how fast the
machine ran it. Here every case runs ``--ticks`` ticks, so two commits (or two machines)
compare: the peak RSS of the process (``ru_maxrss``), its RSS before any convoy (numpy,
numba and the loaded kernels, after a one-convoy warm-up), the rings' size at the end, and
the env's state arrays in bytes per convoy (each array once, views not counted). Actions:
``fixed`` (2 m/s straight on, as ``bench_anchors.py``: the leader drives away, the reads
reach ever farther back) or ``policy`` (the ``paper`` policy acting, ``act_batch``: its
formation at 5 m/s).

    python benchmarks/bench_vector_memory.py [--batches 4096,16384] [--ticks 150]
        [--actions fixed,policy]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")


def _rss_mb() -> float:
    """The process's resident memory now (MB)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _state_bytes(env: Any) -> int:
    """Bytes of the env's arrays and its parts' (each buffer once: views not counted)."""
    import numpy as np

    seen: dict[int, int] = {}
    parts = [env, env.rx, env.channel, env.plant, env.leader, env.events, env.forgers,
             env.ranging]  # fmt: skip
    for part in parts:
        for value in vars(part).values():
            if isinstance(value, np.ndarray):
                owner = value
                while isinstance(owner.base, np.ndarray):
                    owner = owner.base
                seen[id(owner)] = owner.nbytes
    return sum(seen.values())


def case(batch: int, ticks: int, actions: str) -> dict[str, Any]:
    """``ticks`` ticks of ``batch`` convoys (``paper``, 2 followers, PER 0.2)."""
    import numpy as np

    from openconvoy.envs import VectorConvoyEnv
    from openconvoy.policies.spec import load_policy

    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:1])
    warm = VectorConvoyEnv(1, "paper", n_followers=2, max_time_s=1e5, loss=0.2, threads=1)
    obs, _ = warm.reset(seed=0)
    warm.step(np.zeros((1, 2, 2), np.float32))
    policy = load_policy("paper") if actions == "policy" else None
    if policy is not None:
        policy.act_batch(obs)
    del warm
    before = _rss_mb()
    env = VectorConvoyEnv(batch, "paper", n_followers=2, max_time_s=1e5, loss=0.2, threads=1)
    obs, _ = env.reset(seed=0)
    fixed = np.tile(np.array([2.0, 0.0], dtype=np.float32), (batch, 2, 1))
    for _ in range(ticks):
        obs = env.step(fixed if policy is None else policy.act_batch(obs))[0]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"B": batch, "ticks": ticks, "actions": actions, "peak_mb": round(peak, 1),
            "before_mb": round(before, 1), "rss_mb": round(_rss_mb(), 1),
            "window": env.rx.window,
            "state_bytes_per_convoy": round(_state_bytes(env) / batch)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", default="4096,16384")
    ap.add_argument("--ticks", type=int, default=150)
    ap.add_argument("--actions", default="fixed,policy")
    args = ap.parse_args()
    for batch in (int(b) for b in args.batches.split(",")):
        for actions in args.actions.split(","):
            with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
                out = pool.submit(case, batch, args.ticks, actions).result()
            out["load_1min"] = round(os.getloadavg()[0], 2)
            print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
