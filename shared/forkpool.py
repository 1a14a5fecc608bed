"""A fork-context process pool that is safe to start from a program with signal handlers.

A forked worker inherits its parent's Python signal handlers. When the parent has
installed a graceful SIGTERM handler (the recorder does, so `wreckmap-field record`
closes its archive cleanly), the worker inherits it too, and `Pool.terminate()` - which
ends workers with SIGTERM, and which `with Pool(...)` calls on exit - only sets a flag in
them: the parent then waits in `join()` for ever. `fork_pool` restores the default
SIGTERM action in every worker (SIGINT is ignored there: a Ctrl-C in the terminal reaches
the parent, which ends the pool), and on a normal exit it closes the pool and joins the
workers instead of terminating them.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.pool
import signal
from collections.abc import Iterator
from contextlib import contextmanager


def reset_worker_signals() -> None:
    """Pool initializer: default SIGTERM (so `terminate()` ends the worker), SIGINT ignored."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextmanager
def fork_pool(workers: int) -> Iterator[multiprocessing.pool.Pool]:
    """A `multiprocessing.Pool` of `workers` forked processes with default signal handling.

    The workers see the parent's memory as it was at the fork (build shared tables first).
    Leaving the block normally waits for the workers to finish their queue and exit; an
    exception terminates them.
    """
    pool = multiprocessing.get_context("fork").Pool(workers, initializer=reset_worker_signals)
    try:
        yield pool
    except BaseException:
        pool.terminate()
        pool.join()
        raise
    pool.close()
    pool.join()
