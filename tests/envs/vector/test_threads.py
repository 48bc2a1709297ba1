"""The batched step on several threads: the same numbers, bit for bit, whatever the count.

The runs are subprocesses with ``NUMBA_NUM_THREADS`` 1 and 2 (what a user sets), each
digesting every tick's observations, rewards, endings, infos and plant state.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("numba", reason="the batched extra (openconvoy[batched]) is not installed")

from openconvoy.envs import VectorConvoyEnv
from openconvoy.envs.vector.threads import MIN_SLAB, slab_bounds, thread_count

_RUN = """
import hashlib, sys
import numpy as np
from openconvoy.envs import VectorConvoyEnv

B = int(sys.argv[1])
env = VectorConvoyEnv(B, "paper", loss=0.3, max_time_s=1.5)  # episodes end: autoreset
slabs = 0 if env._slabs is None else len(env._slabs.bounds)
rng = np.random.default_rng(7)
digest = hashlib.sha256()
ended = 0
obs, _ = env.reset(seed=3)
digest.update(obs.tobytes())
for _ in range(45):
    a = (rng.random((B, 2, 2)) * [3.0, 0.2] - [0.0, 0.1]).astype(np.float32)
    obs, rew, term, trunc, info = env.step(a)
    ended += int((term | trunc).sum())
    for x in (obs, rew, term, trunc, env.own, info["mode"], info["msgs_received"], info["msgs_lost"]):
        digest.update(np.ascontiguousarray(x).tobytes())
print(env.threads, slabs, ended, digest.hexdigest())
"""


def _run(threads: int, B: int) -> list[str]:
    env = {**os.environ, "NUMBA_NUM_THREADS": str(threads)}
    out = subprocess.run(
        [sys.executable, "-c", _RUN, str(B)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    return out.stdout.split()


def test_one_and_two_threads_give_identical_runs() -> None:
    B = 2 * MIN_SLAB
    one, two = _run(1, B), _run(2, B)
    assert one[:2] == ["1", "0"]  # whole, on one thread
    if len(os.sched_getaffinity(0)) >= 2:
        assert two[:2] == ["2", "2"]  # two slabs, one thread each
    assert int(one[2]) >= B  # every convoy's episode ended and was reset in the run
    assert one[2:] == two[2:]


def test_slab_bounds_cover_the_batch_in_slabs_of_at_least_min_slab() -> None:
    assert slab_bounds(100, 4) == [(0, 100)]
    assert slab_bounds(3 * MIN_SLAB - 1, 4) == [(0, 767), (767, 1535)]
    bounds = slab_bounds(16_384, 3)
    assert bounds == [(0, 5461), (5461, 10922), (10922, 16384)]


def test_thread_count_is_the_cores_given_capped_by_numba_num_threads(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cores = len(os.sched_getaffinity(0))
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    assert thread_count(None) == cores
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    assert thread_count(None) == 1
    assert thread_count(3) == 3
    with pytest.raises(ValueError, match="positive integer"):
        thread_count(0)


def test_slabs_in_one_process_match_the_whole_step_and_keep_the_plant_head() -> None:
    B = 2 * MIN_SLAB
    whole = VectorConvoyEnv(B, "paper", loss=0.2, threads=1)
    cut = VectorConvoyEnv(B, "paper", loss=0.2, threads=2)
    assert whole._slabs is None and cut._slabs is not None
    rng = np.random.default_rng(0)
    whole.reset(seed=11)
    cut.reset(seed=11)
    for _ in range(4):
        a = (rng.random((B, 2, 2)) * [3.0, 0.1]).astype(np.float32)
        ow, rw, *_ = whole.step(a)
        oc, rc, *_ = cut.step(a)
        np.testing.assert_array_equal(oc, ow)
        np.testing.assert_array_equal(rc, rw)
        np.testing.assert_array_equal(cut.own, whole.own)
    assert cut.plant.head[0] == whole.plant.head[0] == 4 % whole.plant.depth
    cut.close()
