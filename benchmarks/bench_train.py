"""``openconvoy train`` on the batched simulator beside SuperSuit's per-convoy path, the
same budget, and validation batched beside run by run (issue 14, item 5).

Runs the default residual training (``TrainConfig()``: PPO, 32 convoys x 2 followers,
domain randomization, validation of every checkpoint) for ``--steps`` agent steps twice,
``vec_env = "batched"`` and ``"supersuit"``, and validates one trained file on the
default grid (PER 0.3, 0.6 x seeds 1000-1002) both ways. Prints JSON lines: wall and CPU
seconds (``process_time``, steadier on a shared machine) of the whole ``train`` call and
of ``learn``, and the load average at the start (the machine is shared).

    python benchmarks/bench_train.py [--steps 100000]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

from openconvoy.train.config import TrainConfig
from openconvoy.train.train import train
from openconvoy.train.validate import validate


def _timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn(*args, **kwargs)
    return result, round(time.perf_counter() - wall, 1), round(time.process_time() - cpu, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100_000)
    args = ap.parse_args()
    base = TrainConfig(total_steps=args.steps, checkpoint_every=max(1, args.steps // 2))
    with tempfile.TemporaryDirectory() as tmp:
        for vec_env in ("batched", "supersuit"):
            load = os.getloadavg()[0]
            config = dataclasses.replace(base, vec_env=vec_env)
            result, wall, cpu = _timed(train, config, Path(tmp) / vec_env, progress_bar=False)
            line = {
                "case": f"train {vec_env}",
                "steps": result.steps,
                "wall_s": wall,
                "cpu_s": cpu,
                "learn_wall_s": round(result.wall_s, 1),
                "load_1min": round(load, 2),
            }
            print(json.dumps(line), flush=True)
        policy = Path(tmp) / "batched" / "policy.zip"
        grid = (base.validation_pers, base.validation_seeds)
        for batched in (True, False):
            load = os.getloadavg()[0]
            _, wall, cpu = _timed(validate, policy, *grid, batched=batched)
            case = "validate batched" if batched else "validate run by run"
            runs = len(grid[0]) * len(grid[1])
            line = {"case": case, "runs": runs, "wall_s": wall, "cpu_s": cpu, "load_1min": load}
            print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
