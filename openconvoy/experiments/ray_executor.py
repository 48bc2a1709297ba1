"""The ``ray`` executor: each task a Ray task on a cluster (the ``openconvoy[cluster]`` extra).

This is the only module that imports Ray, and only when a ``RayExecutor`` is made.

A task runs as a streaming-generator Ray task that first yields where it runs (pid, host,
IP, Ray node) and then the run's result, so when a worker or its node dies mid-run the
driver still names the worker the run was lost on. Results travel back through Ray's
object store as Python objects (logs and files as bytes); workers need no file system
shared with the driver, only the same ``openconvoy`` installed.

Without an address (and no ``RAY_ADDRESS`` in the environment) the executor starts a
private cluster of this machine's cores and stops it on ``close``; with one it connects
to that cluster (``auto``: the one ``ray start`` made on this machine) and only
disconnects. A process already connected (``ray.init`` done) is used as it is.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from typing import Any

from openconvoy.core.errors import DependencyMissing, LinkError
from openconvoy.experiments.executor import (
    Executor,
    Task,
    TaskFailure,
    error_line,
    guarded,
    outcome,
    worker_location,
)

EXTRA_HINT = "pip install 'openconvoy[cluster]'"


def import_ray() -> Any:
    """The ``ray`` module, or one clear error naming the extra that installs it."""
    try:
        import ray
    except ImportError:
        raise DependencyMissing(
            f"the ray executor needs Ray, which is not installed: {EXTRA_HINT}"
        ) from None
    return ray


def _run(fn: Any, arg: Any) -> Iterator[Any]:
    """The Ray task: where it runs first, then ``fn(arg)`` (an exception as a _Failed)."""
    import ray

    ctx = ray.get_runtime_context()
    where = f"Ray worker {worker_location()} {ray.util.get_node_ip_address()}, node {ctx.get_node_id()[:8]}"
    yield where
    yield guarded(fn, arg, where)


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A ``HOST:PORT`` address that nothing answers is one error line now, not Ray's
    minutes of reconnecting."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or "://" in address:
        return  # "auto" and the like: Ray resolves them itself
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise LinkError(
            f"cannot reach the Ray cluster at {address}: {error_line(exc, frame=False)}"
        ) from None


class RayExecutor(Executor):
    """Tasks on a Ray cluster (see the module docstring); ``jobs`` caps the tasks in
    flight (default: the cluster's CPUs when connecting), ``max_retries`` reruns a task
    whose worker died (Ray's system-failure retries; exceptions are never retried)."""

    kind = "ray"

    def __init__(
        self, address: str | None = None, jobs: int | None = None, max_retries: int = 0
    ) -> None:
        ray = import_ray()
        self._ray = ray
        self._owns = False
        if not ray.is_initialized():
            address = address or os.environ.get("RAY_ADDRESS") or "local"
            kwargs: dict[str, Any] = {}
            if address == "local":
                kwargs["include_dashboard"] = False
            else:
                _check_reachable(address)
            try:
                ray.init(
                    address=address, log_to_driver=False, logging_level=logging.WARNING, **kwargs
                )
            except ConnectionError as exc:
                raise LinkError(
                    f"cannot reach the Ray cluster at {address}: {error_line(exc, frame=False)}"
                ) from None
            except Exception as exc:  # noqa: BLE001 - Ray raises bare Exception on a slow start
                # e.g. "The current node timed out during startup" on a busy machine: one
                # line naming the cluster and Ray's reason, not a traceback.
                where = "a private cluster of this machine" if address == "local" else address
                raise LinkError(
                    f"the Ray cluster ({where}) did not start: {error_line(exc, frame=False)}"
                ) from None
            self._owns = address == "local"
        self.address = ray.get_runtime_context().gcs_address
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self._slots = jobs or max(1, cpus)
        self._remote = ray.remote(_run).options(
            num_returns="streaming", num_cpus=1, max_retries=max_retries
        )
        self._pending: dict[Any, Task] = {}
        self._where: dict[Any, str] = {}

    @property
    def slots(self) -> int:
        return self._slots

    def submit(self, task: Task) -> None:
        self._pending[self._remote.remote(task.fn, task.arg)] = task

    def wait_one(self) -> tuple[Task, Any]:
        ray = self._ray
        while True:
            ready, _ = ray.wait(list(self._pending), num_returns=1)
            gen = ready[0]
            task = self._pending[gen]
            try:
                value = ray.get(next(gen))
            except StopIteration:  # ended without a result: cannot happen with _run
                value = TaskFailure(
                    task.label, self._where.get(gen, "a Ray worker"), "the task returned nothing"
                )
            except ray.exceptions.RayError as exc:
                cause = getattr(exc, "cause", None)
                where = self._where.get(gen, "a Ray worker that had not started the run")
                error = (
                    error_line(cause)
                    if isinstance(cause, BaseException)
                    else error_line(exc, frame=False)
                )
                value = TaskFailure(task.label, where, error)
            else:
                if gen not in self._where:
                    self._where[gen] = value
                    continue
                value = outcome(task, value)
            del self._pending[gen]
            self._where.pop(gen, None)
            return task, value

    def close(self) -> None:
        ray = self._ray
        for gen in self._pending:
            try:
                ray.cancel(gen, force=True)
            except Exception:  # noqa: BLE001 - already ended or its worker gone
                pass
        self._pending.clear()
        self._where.clear()
        if self._owns and ray.is_initialized():
            ray.shutdown()
            self._owns = False
