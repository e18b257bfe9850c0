"""Order-preserving map over worker processes, with a progress bar."""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable, Sequence
from typing import Any

from tqdm import tqdm

from .errors import interrupts_deferred

MAX_WORKERS = 8


def default_workers() -> int:
    """One worker per available core, at most ``MAX_WORKERS``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS))


def _quiet_worker() -> None:
    """Ctrl-C, a hangup and SIGTERM are the parent's to handle (they reach a terminal job's
    whole process group). A worker must not die of them: an idle worker holds the task
    queue's lock while it waits, and a worker that dies holding it deadlocks the pool
    (measured: a SIGTERM to the group during the tensors hung ``Pool.terminate()`` in a
    semaphore acquire). The parent ends the pool with close() + join() instead."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def map_jobs(
    function: Callable[[Any], Any],
    jobs: Sequence[Any],
    workers: int | None = None,
    description: str = "",
    progress: bool = False,
) -> list[Any]:
    """``[function(job) for job in jobs]``, in order, over ``workers`` processes.

    ``function`` must be a module-level function (it is pickled). One worker, or
    a single job, runs in this process. Workers are forked where the platform
    allows it (no re-import), spawned elsewhere.
    """
    workers = default_workers() if workers is None else max(1, workers)
    bar = tqdm(total=len(jobs), desc=description, disable=not progress)
    if workers == 1 or len(jobs) <= 1:
        results = []
        for job in jobs:
            results.append(function(job))
            bar.update()
        bar.close()
        return results
    method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
    pool = None
    try:
        with interrupts_deferred():  # Ctrl-C inside fork() is lost in an at-fork hook
            pool = multiprocessing.get_context(method).Pool(min(workers, len(jobs)), _quiet_worker)
        results = []
        for result in pool.imap(function, jobs, chunksize=1):
            results.append(result)
            bar.update()
    finally:
        # close + join lets the workers finish the jobs already queued and exit
        # normally, also after an interrupt (which costs that wait): terminate() would
        # send them SIGTERM, which they ignore (see _quiet_worker).
        if pool is not None:
            pool.close()
            pool.join()
        bar.close()
    return results
