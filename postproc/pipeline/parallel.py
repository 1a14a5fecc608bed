"""Spreading a stage's per-image work over the workers of the backend the stage runs on.

A map function has the signature `map_fn(fn, items) -> list` and returns `[fn(item) for
item in items]` in order. `fn` must be a picklable top-level function whose items are
paths and options (never images: data moves through the shared filesystem), and every
call must write its outputs atomically, so that a call repeated on another worker (after
a worker died) gives the same files.

- `serial`: one after another in this process (the inline backend).
- `process`: a pool of N spawned processes on this machine (the local process-pool
  backend; the stage's own process waits meanwhile).
- `dask`: inside a stage task on a Dask distributed worker, each item becomes a Dask task
  submitted through `distributed.worker_client()`, which secedes the stage task's thread
  from the worker's pool while it waits (its slot runs items too) and rejoins after: the
  items spread over every worker, and those of a worker that dies are rescheduled on
  the others by the scheduler.

The runner puts a `ParallelSpec` in each task's context (`context["parallel"]`); the stage
adapters turn it into a map function with `make_map`.
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from shared.errors import InputError
from shared.progress import MapFn, serial_map

log = logging.getLogger(__name__)

KINDS = ("serial", "process", "dask")


@dataclass(frozen=True, kw_only=True)
class ParallelSpec:
    """How a stage spreads its per-image work (picklable; travels in the task context).

    kind: "serial", "process" (a local pool of `workers` processes) or "dask" (tasks on
    the Dask cluster the stage runs on); workers: pool size for "process".
    """

    kind: Literal["serial", "process", "dask"] = "serial"
    workers: int = 1


def process_map(workers: int) -> MapFn:
    """A map function running the items in a pool of `workers` spawned processes (a fresh
    pool per call: spawned, so nothing is shared by fork with the caller's threads)."""
    if workers < 1:
        raise InputError(f"process map: {workers} workers (expected at least 1)")

    def run(fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
        if workers == 1 or len(items) <= 1:
            return serial_map(fn, items)
        from shared.progress import progress

        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            max_workers=min(workers, len(items)), mp_context=context
        ) as pool:
            futures = [pool.submit(fn, item) for item in items]
            done = concurrent.futures.as_completed(futures)
            name = getattr(fn, "__name__", "task")
            for _ in progress(done, total=len(futures), desc=name, unit="item"):
                pass
            return [f.result() for f in futures]

    return run


def in_dask_worker() -> bool:
    """True when called from a task running on a Dask distributed worker."""
    try:
        from distributed import get_worker
    except ImportError:
        return False
    try:
        get_worker()
    except ValueError:  # distributed's answer outside a worker
        return False
    return True


def dask_map(fn: Callable[[Any], Any], items: list[Any]) -> list[Any]:
    """The items as separate Dask tasks on the cluster this task runs on (see the module
    docstring); outside a Dask worker they run serially here (with a warning)."""
    if not in_dask_worker():
        log.warning("dask map called outside a Dask worker: running %d items here", len(items))
        return serial_map(fn, items)
    if not items:
        return []
    from distributed import as_completed, worker_client

    from shared.progress import progress

    name = getattr(fn, "__name__", "task")
    # Fresh keys: a rerun of a stage is a new computation, never a cached result.
    batch = uuid.uuid4().hex[:8]
    keys = [f"{name}-{batch}-{k}" for k in range(len(items))]
    with worker_client() as client:
        futures = client.map(fn, items, key=keys, pure=False)
        try:
            for _ in progress(as_completed(futures), total=len(futures), desc=name, unit="item"):
                pass
            results = client.gather(futures)
        finally:
            client.cancel(futures)
    return list(results)


def make_map(spec: ParallelSpec | None) -> MapFn:
    """The map function for `spec` (None: serial)."""
    if spec is None or spec.kind == "serial":
        return serial_map
    if spec.kind == "process":
        return process_map(spec.workers)
    if spec.kind == "dask":
        return dask_map
    raise InputError(f"parallel kind {spec.kind!r}: expected one of {', '.join(KINDS)}")
