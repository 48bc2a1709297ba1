"""Where the runs of a sweep, a tuning study or several trainings execute: the executor seam.

A task is one whole run: a picklable function and its argument, sent to a worker; what the
function returns (a run's log and metrics as bytes, a trial's objective, a training run's
files) comes back to the driver, and only the driver writes the run directory, so nothing
depends on a file system shared with the workers.

- ``local`` (the default): processes on this machine (``jobs``, default the cores this
  process may use; ``jobs = 1`` runs every task in this process).
- ``ray``: tasks on a Ray cluster (``openconvoy.experiments.ray_executor``; the
  ``openconvoy[cluster]`` extra): ``address`` of a running cluster (``HOST:6379``, ``auto``
  for the one ``ray start`` made on this machine), or none for a private cluster of this
  machine's cores that lives as long as the command.

A task that fails (an exception in the run, or a worker or node lost) comes back as a
``TaskFailure`` naming the run, the worker and the error line; the other tasks go on.
In an experiment file the executor is the optional ``[executor]`` table::

    [executor]
    kind = "ray"
    address = "10.0.0.5:6379"
    jobs = 64          # tasks in flight at once (default: the cluster's CPUs)
    max_retries = 0    # Ray: reruns of a task whose worker died (default 0)
    batched = true     # sweeps and tune: a policy's runs as batches (default: where exact)

``batched`` (``--batched/--no-batched``) groups a sweep's or a trial's runs of one policy
into a few tasks, each a ``VectorConvoyEnv`` of many convoys (``experiments.batched.run``):
unset, wherever the results are the per-run path's to the bit (classical policies);
``true`` also for policies whose ``act_batch`` is only close to their ``act``; ``false``
one ``ConvoyEnv`` task per run. Configurations the batched env refuses run per run.
"""

from __future__ import annotations

import os
import socket
import traceback
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from openconvoy.core.errors import ConfigError

EXECUTOR_KINDS = ("local", "ray")


@dataclass(frozen=True)
class ExecutorConfig:
    """Which executor runs the tasks, and how (see the module docstring)."""

    kind: str = "local"
    address: str | None = None
    jobs: int | None = None
    max_retries: int = 0
    batched: bool | None = None

    def __post_init__(self) -> None:
        if self.kind not in EXECUTOR_KINDS:
            raise ConfigError(
                f"unknown executor {self.kind!r}; expected one of {', '.join(EXECUTOR_KINDS)}"
            )
        if self.address is not None and self.kind != "ray":
            raise ConfigError("an executor address needs the ray executor (--executor ray)")
        if self.jobs is not None and self.jobs < 1:
            raise ConfigError(f"jobs must be at least 1, got {self.jobs}")
        if self.max_retries < 0:
            raise ConfigError(f"max_retries must be >= 0, got {self.max_retries}")


@dataclass(frozen=True)
class Task:
    """One whole run: ``fn(arg)`` on a worker; ``label`` names it in progress and errors."""

    label: str
    fn: Callable[[Any], Any]
    arg: Any


@dataclass(frozen=True)
class TaskFailure:
    """A task that did not return: which run, on which worker, and the error line."""

    label: str
    where: str
    error: str

    def line(self) -> str:
        return f"{self.label}: {self.error} (on {self.where})"


class TasksFailed(RuntimeError):
    """Some tasks failed; the message has one line per failed task."""

    def __init__(
        self, failures: Sequence[TaskFailure], total: int, kept: str = "", noun: str = "runs"
    ) -> None:
        self.failures = list(failures)
        head = f"{len(self.failures)} of {total} {noun} failed" + (f"; {kept}" if kept else "")
        super().__init__("\n".join([head, *("  " + f.line() for f in self.failures)]))


@dataclass(frozen=True)
class _Failed:
    """What ``guarded`` returns from the worker for an exception (the driver adds the label)."""

    where: str
    error: str


def worker_location() -> str:
    """This process as an error names it: ``pid N on HOST``."""
    return f"pid {os.getpid()} on {socket.gethostname()}"


def error_line(exc: BaseException, frame: bool = True) -> str:
    """``Type: first line of the message [file:line of the innermost frame]`` (the frame
    only with ``frame``: not for errors the driver's own machinery raises)."""
    text = str(exc).strip().splitlines()
    out = type(exc).__name__ + (f": {text[0]}" if text else "")
    frames = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ and frame else []
    if frames:
        out += f" [{os.path.basename(frames[-1].filename)}:{frames[-1].lineno}]"
    return out


_progress_put: Callable[[tuple[str, float]], None] | None = None
"""Where this process sends its tasks' partial progress (None: nowhere; only whole tasks
count, as on Ray)."""
_running: str = ""
"""The label of the task this process runs now (``guarded`` sets it)."""


def report_progress(fraction: float) -> None:
    """The running task is ``fraction`` (0..1) done: the driver's progress bar moves by
    that share of the task's weight (a batch of runs moves run by run, not all at once).
    A no-op where the executor carries no progress."""
    if _progress_put is not None and _running:
        _progress_put((_running, min(1.0, max(0.0, float(fraction)))))


def _send_progress_to(put: Callable[[tuple[str, float]], None] | None) -> None:
    """Make this process report progress through ``put`` (a worker pool's initializer)."""
    global _progress_put
    _progress_put = put


def guarded(fn: Callable[[Any], Any], arg: Any, where: str | None = None, label: str = "") -> Any:
    """``fn(arg)`` on a worker, an exception returned as a ``_Failed`` instead of raised
    (so one bad run is reported, not the whole pool's); ``label``: the task's, which its
    ``report_progress`` calls carry."""
    global _running
    _running = label
    try:
        return fn(arg)
    except Exception as exc:  # noqa: BLE001 - reported to the driver, which names the run
        return _Failed(where or worker_location(), error_line(exc))
    finally:
        _running = ""


def outcome(task: Task, value: Any) -> Any:
    """A worker's return value as the driver sees it (``_Failed`` becomes a TaskFailure)."""
    if isinstance(value, _Failed):
        return TaskFailure(task.label, value.where, value.error)
    return value


class Executor(ABC):
    """Runs tasks, at most ``slots`` at once; results come back as each task ends."""

    kind: str = ""

    @property
    @abstractmethod
    def slots(self) -> int:
        """Tasks worth keeping in flight (the workers available)."""

    @abstractmethod
    def submit(self, task: Task) -> None:
        """Start ``task`` (it may wait for a free worker)."""

    @abstractmethod
    def wait_one(self) -> tuple[Task, Any]:
        """Block until a submitted task ends: ``(task, its result or a TaskFailure)``."""

    @abstractmethod
    def close(self) -> None:
        """Stop: cancel what has not ended, release the workers."""

    def progress_queue(self) -> Any | None:
        """A queue on which ``(task label, fraction done)`` arrives while tasks run
        (``report_progress``), or None: this executor reports whole tasks only."""
        return None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def map(
        self,
        tasks: Sequence[Task],
        progress: bool = True,
        desc: str = "",
        unit: str = "run",
        on_result: Callable[[int, Any], None] | None = None,
        weights: Sequence[int] | None = None,
        bar: Any = None,
    ) -> list[Any]:
        """Every task's result (or TaskFailure), in task order, whatever order they end in;
        a progress bar over tasks (counted in ``unit``s) on stderr with ``progress``;
        ``on_result(i, result)`` as task ``i`` ends (so a caller keeps what finished
        when it is interrupted); ``weights[i]``: the ``unit``s task ``i`` counts for (a
        batch of runs), 1 each by default. A task's ``report_progress`` moves the bar by
        that share of its weight as it runs (local executor). ``bar``: an object with
        tqdm's ``n``, ``refresh``, ``set_postfix_str`` and ``close`` instead of the stderr bar."""
        index = {id(t): i for i, t in enumerate(tasks)}
        results: list[Any] = [None] * len(tasks)
        todo = deque(tasks)
        weight = list(weights) if weights is not None else [1] * len(tasks)
        if bar is None:
            bar = _bar(sum(weight), progress, desc, unit, partial=any(w > 1 for w in weight))
        else:
            progress = True
        meter = _Meter(bar, {t.label: i for i, t in enumerate(tasks)}, weight)
        listener = _listen(self.progress_queue() if progress else None, meter)
        in_flight = failed = 0
        try:
            while todo or in_flight:
                while todo and in_flight < self.slots:
                    self.submit(todo.popleft())
                    in_flight += 1
                task, value = self.wait_one()
                in_flight -= 1
                results[index[id(task)]] = value
                if on_result is not None:
                    on_result(index[id(task)], value)
                if isinstance(value, TaskFailure):
                    failed += 1
                    bar.set_postfix_str(f"{failed} failed", refresh=False)
                meter.finished(index[id(task)])
        finally:
            listener()
            bar.close()
        return results


class _Meter:
    """The progress bar's count: each task credited with the share of its weight it
    reported done (``report_progress``), and all of it when it ends; reports that arrive
    after the end, or go backwards, change nothing. The bar's ``n`` is set, never summed
    from float steps, so it ends at its total exactly. Thread-safe (a listener feeds it)."""

    def __init__(self, bar: Any, by_label: dict[str, int], weight: Sequence[int]) -> None:
        import threading

        self.bar, self.by_label, self.weight = bar, by_label, list(weight)
        self.total = sum(self.weight)
        self.credited = [0.0] * len(self.weight)
        self.done = [False] * len(self.weight)
        self.sum = 0.0  # of ``credited``
        self.lock = threading.Lock()

    def partial(self, label: str, fraction: float) -> None:
        """Task ``label`` reports ``fraction`` of itself done."""
        i = self.by_label.get(label)
        if i is not None:
            self._credit(i, fraction * self.weight[i], ended=False)

    def finished(self, i: int) -> None:
        """Task ``i`` ended: the rest of its weight."""
        self._credit(i, float(self.weight[i]), ended=True)

    def _credit(self, i: int, units: float, ended: bool) -> None:
        with self.lock:
            if self.done[i] or units <= self.credited[i]:
                self.done[i] = self.done[i] or ended
                return
            self.sum += units - self.credited[i]
            self.credited[i] = units
            self.done[i] = ended
            self.bar.n = self.total if all(self.done) else min(self.sum, self.total)
            self.bar.refresh()


def _listen(queue: Any | None, meter: _Meter) -> Callable[[], None]:
    """Feed ``meter`` from ``queue`` on a thread until the returned function is called
    (which stops it); a no-op without a queue."""
    if queue is None:
        return lambda: None
    import threading

    def drain() -> None:
        while (item := queue.get()) is not None:
            meter.partial(*item)

    thread = threading.Thread(target=drain, name="openconvoy-progress", daemon=True)
    thread.start()

    def stop() -> None:
        queue.put(None)
        thread.join(5.0)

    return stop


PARTIAL_BAR = "{l_bar}{bar}| {n:.1f}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]"
"""The bar's line where tasks move it by fractions (a batch of runs): one decimal."""


def _bar(total: int, enabled: bool, desc: str, unit: str = "run", partial: bool = False) -> Any:
    from tqdm import tqdm

    return tqdm(
        total=total,
        unit=unit,
        desc=desc or None,
        disable=not enabled,
        bar_format=PARTIAL_BAR if partial else None,
    )


class LocalExecutor(Executor):
    """Tasks on ``jobs`` spawned processes of this machine (1: in this process).

    A worker process that dies (a crash, the OOM killer) breaks Python's process pool,
    and every task then in flight with it; the pool cannot say whose worker died. So a
    fresh pool takes the next tasks while those in flight are run again one at a time in
    a pool of their own: the one whose worker dies again alone is reported lost, the
    others come back as if nothing had happened."""

    kind = "local"

    def __init__(self, jobs: int | None = None) -> None:
        self.jobs = jobs or available_cores()
        self._queue: deque[Task] = deque()
        self._pool: Any = None
        self._futures: dict[Any, tuple[Task, Any]] = {}  # future -> (task, its pool)
        self._suspects: deque[Task] = deque()  # in flight when a pool broke
        self._solo_pool: Any = None
        self._solo: tuple[Any, Task] | None = None  # the suspect running alone
        self._progress: Any = None  # the queue workers report progress on, once asked

    @property
    def slots(self) -> int:
        return self.jobs

    def submit(self, task: Task) -> None:
        if self.jobs == 1:
            self._queue.append(task)
            return
        from concurrent.futures.process import BrokenProcessPool

        if self._pool is None:
            self._pool = _process_pool(self.jobs, self._progress)
        try:
            future = self._pool.submit(guarded, task.fn, task.arg, None, task.label)
        except BrokenProcessPool:
            # A worker died after the last result was taken and before this submit: the
            # tasks still in flight with the old pool come back broken in wait_one (and run
            # again alone); this one goes to a fresh pool.
            self._pool.shutdown(wait=False)  # (not cancel_futures: wait_one reads them)
            self._pool = _process_pool(self.jobs, self._progress)
            future = self._pool.submit(guarded, task.fn, task.arg, None, task.label)
        self._futures[future] = (task, self._pool)

    def wait_one(self) -> tuple[Task, Any]:
        if self.jobs == 1:
            task = self._queue.popleft()
            return task, outcome(
                task, guarded(task.fn, task.arg, f"the driver, {worker_location()}", task.label)
            )
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        while True:
            if self._solo is None and self._suspects:
                if self._solo_pool is None:
                    self._solo_pool = _process_pool(1, self._progress)
                task = self._suspects.popleft()
                self._solo = (
                    self._solo_pool.submit(guarded, task.fn, task.arg, None, task.label),
                    task,
                )
            waiting = list(self._futures) + ([self._solo[0]] if self._solo else [])
            done, _ = wait(waiting, return_when=FIRST_COMPLETED)
            fut = next(iter(done))
            if self._solo is not None and fut is self._solo[0]:
                task = self._solo[1]
                self._solo = None
                try:
                    return task, outcome(task, fut.result())
                except BrokenProcessPool as exc:
                    self._solo_pool.shutdown(wait=False, cancel_futures=True)
                    self._solo_pool = None
                    return task, TaskFailure(
                        task.label,
                        "a local worker process, which died running it (alone, on a second try)",
                        error_line(exc, frame=False),
                    )
            task, pool = self._futures.pop(fut)
            try:
                return task, outcome(task, fut.result())
            except BrokenProcessPool:
                if pool is self._pool:
                    pool.shutdown(wait=False, cancel_futures=True)
                    self._pool = None  # the next submit starts a fresh pool
                self._suspects.append(task)

    def progress_queue(self) -> Any:
        """Workers (processes, or this one with ``jobs = 1``) report progress on it; ask
        before the first ``submit`` (the pool's processes are given it as they start)."""
        if self._progress is None:
            import multiprocessing
            import queue

            if self.jobs == 1:
                self._progress = queue.SimpleQueue()
                _send_progress_to(self._progress.put)
            else:
                self._progress = multiprocessing.get_context("spawn").Queue()
        return self._progress

    def close(self) -> None:
        if self.jobs == 1 and self._progress is not None:
            _send_progress_to(None)
        progress, self._progress = self._progress, None
        for pool in (self._pool, self._solo_pool):
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        self._pool = self._solo_pool = self._solo = None
        if progress is not None and self.jobs > 1:
            progress.close()  # after the pools: no worker writes to it any more
        self._futures.clear()
        self._queue.clear()
        self._suspects.clear()


def _process_pool(workers: int, progress: Any = None) -> Any:
    """A pool of ``workers`` spawned processes, each reporting progress on ``progress``
    (a multiprocessing queue; None: none)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # spawn: workers start clean (no inherited threads or open files). A queue reaches a
    # worker only as it starts (an initializer argument), never inside a task.
    context = multiprocessing.get_context("spawn")
    if progress is None:
        return ProcessPoolExecutor(max_workers=workers, mp_context=context)
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=context,
        initializer=_send_progress_to,
        initargs=(progress.put,),
    )


def with_flags(
    config: ExecutorConfig | None,
    kind: str | None,
    address: str | None,
    jobs: int | None,
    batched: bool | None = None,
) -> ExecutorConfig:
    """``config`` (an experiment file's ``[executor]``, or the default) with the command
    line's ``--executor``, ``--address``, ``--jobs`` and ``--batched`` on top (None: not
    given)."""
    import dataclasses

    config = config or ExecutorConfig()
    changes: dict[str, Any] = {}
    if kind is not None and kind != config.kind:
        changes.update(kind=kind, address=None)
    if address is not None:
        changes["address"] = address
    if jobs is not None:
        changes["jobs"] = jobs
    if batched is not None:
        changes["batched"] = batched
    return dataclasses.replace(config, **changes) if changes else config


def make_executor(config: ExecutorConfig | None = None) -> Executor:
    """The executor ``config`` describes (default: local, on every core)."""
    config = config or ExecutorConfig()
    if config.kind == "ray":
        from openconvoy.experiments.ray_executor import RayExecutor

        return RayExecutor(address=config.address, jobs=config.jobs, max_retries=config.max_retries)
    return LocalExecutor(config.jobs)


def available_cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
