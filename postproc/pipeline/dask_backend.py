"""Where pipeline tasks run: this process, a local process pool, Dask distributed, SLURM.

Every backend has the same small interface (`submit`, `wait_any`, `result`, `close`,
`description`); the runner keeps the stage graph and submits a task when its inputs are
done. Tasks carry paths and options only: every worker must see the project's input and
output folders at the same paths (a shared filesystem), and images never travel through
the scheduler.

- `local` (default), 1 worker: tasks run one after another in this process (no server).
- `local` with N > 1 workers: a pool of N processes on this machine (no server).
- `tcp://HOST:8786` (or `tls://...`): an existing Dask distributed scheduler. Start one
  with `dask scheduler` and workers with `dask worker tcp://HOST:8786 --nthreads 1` on
  machines that mount the project folders at the same paths. A worker that dies
  mid-stage has its task rescheduled on another worker by Dask; the partial folder of
  the dead attempt is never renamed into place.
- `slurm`: dask-jobqueue starts workers as SLURM jobs (settings under `cluster:` in the
  project file: queue, account, cores, memory, walltime, jobs), then as above.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from collections.abc import Callable
from typing import Any

from postproc.pipeline.parallel import ParallelSpec
from postproc.pipeline.project import ClusterSpec
from shared.errors import InputError


class InlineBackend:
    """Run each task at submission, in this process (progress bars and logs stay visible)."""

    description = "in this process"
    # How a stage spreads its per-image work (`postproc.pipeline.parallel`).
    parallel = ParallelSpec(kind="serial")

    def submit(
        self, key: str, fn: Callable[..., Any], *args: Any
    ) -> concurrent.futures.Future[Any]:
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        try:
            future.set_result(fn(*args))
        except Exception as error:  # delivered to the runner through result()
            future.set_exception(error)
        return future

    def wait_any(self, handles: list[Any]) -> list[Any]:
        return [h for h in handles if h.done()] or handles[:1]

    def result(self, handle: Any) -> Any:
        return handle.result()

    def close(self) -> None:
        pass


class ProcessBackend:
    """A pool of `workers` processes on this machine (spawned: no state shared by fork)."""

    def __init__(self, workers: int) -> None:
        self.pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn")
        )
        self.description = f"local pool of {workers} processes"
        self.parallel = ParallelSpec(kind="process", workers=workers)

    def submit(self, key: str, fn: Callable[..., Any], *args: Any) -> Any:
        return self.pool.submit(fn, *args)

    def wait_any(self, handles: list[Any]) -> list[Any]:
        done, _ = concurrent.futures.wait(handles, return_when=concurrent.futures.FIRST_COMPLETED)
        return list(done)

    def result(self, handle: Any) -> Any:
        return handle.result()

    def close(self) -> None:
        self.pool.shutdown(wait=True)


class DaskBackend:
    """Tasks as Dask futures on a distributed cluster (`client` from an address or SLURM)."""

    def __init__(self, client: Any, *, cluster: Any = None, description: str = "") -> None:
        self.client = client
        self.cluster = cluster
        self.description = description or f"dask {client.scheduler.address}"
        self.parallel = ParallelSpec(kind="dask")

    def submit(self, key: str, fn: Callable[..., Any], *args: Any) -> Any:
        import uuid

        # pure=False and a fresh key: a rerun of the same stage is a new computation.
        return self.client.submit(fn, *args, key=f"{key}-{uuid.uuid4().hex[:8]}", pure=False)

    def wait_any(self, handles: list[Any]) -> list[Any]:
        from distributed import wait

        done, _ = wait(handles, return_when="FIRST_COMPLETED")
        return list(done)

    def result(self, handle: Any) -> Any:
        try:
            return handle.result()
        finally:
            # Let Dask forget it: a finished stage must not be recomputed when the worker
            # holding its (tiny) result dies later.
            handle.release()

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def slurm_cluster_class() -> Any:
    """dask-jobqueue's SLURMCluster, imported without letting the import take Ctrl-C:
    importing dask_jobqueue installs its own SIGINT handler, which would stop
    `wreckmap-post run` from ending its stages cleanly (KeyboardInterrupt, exit 130)."""
    import signal
    import threading

    handler = signal.getsignal(signal.SIGINT)
    try:
        from dask_jobqueue.slurm import SLURMCluster
    finally:
        if threading.current_thread() is threading.main_thread() and handler is not None:
            signal.signal(signal.SIGINT, handler)
    return SLURMCluster


def slurm_cluster(spec: ClusterSpec, **scheduler_options: Any) -> Any:
    """A dask-jobqueue SLURMCluster: one worker per job running one stage at a time (one
    thread), the job's cores left to the stage's own threads (COLMAP, OpenCV, numpy)."""
    SLURMCluster = slurm_cluster_class()
    return SLURMCluster(
        queue=spec.queue,
        account=spec.account,
        cores=1,
        processes=1,
        job_cpu=spec.cores,
        memory=spec.memory,
        walltime=spec.walltime,
        job_extra_directives=list(spec.job_extra_directives),
        scheduler_options=scheduler_options or None,
    )


def make_backend(
    scheduler: str,
    *,
    workers: int = 1,
    cluster: ClusterSpec | None = None,
    connect_timeout_s: float = 20.0,
) -> Any:
    """The backend for `--scheduler` (local, tcp://HOST:PORT, tls://..., slurm).

    workers: local processes (1: this process) or SLURM jobs (1: `cluster.jobs`).
    connect_timeout_s: how long to wait for a Dask scheduler to answer, seconds.
    """
    if workers < 1:
        raise InputError(f"--workers {workers}: expected at least 1")
    if scheduler == "local":
        return InlineBackend() if workers == 1 else ProcessBackend(workers)
    if scheduler.startswith(("tcp://", "tls://", "inproc://")):
        from distributed import Client

        try:
            client = Client(scheduler, timeout=f"{connect_timeout_s}s")
        except OSError as error:
            raise InputError(
                f"--scheduler {scheduler}: no Dask scheduler answers there ({error}); start one "
                "with `dask scheduler` and workers with `dask worker ADDRESS`"
            ) from None
        return DaskBackend(client)
    if scheduler == "slurm":
        from distributed import Client

        spec = cluster or ClusterSpec()
        slurm = slurm_cluster(spec)
        slurm.scale(jobs=workers if workers > 1 else spec.jobs)
        return DaskBackend(Client(slurm), cluster=slurm, description="dask-jobqueue SLURM")
    raise InputError(
        f"--scheduler {scheduler!r}: expected 'local', 'slurm' or a Dask address tcp://HOST:PORT"
    )
