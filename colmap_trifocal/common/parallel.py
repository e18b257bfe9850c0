"""Order-preserving map over worker threads or forked processes, with a progress bar;
BLAS kept single-threaded.

Most of the calibration's parallel jobs (the focal search, the lens search, the
diagnosis) spend their time in OpenCV, which releases the GIL, so threads use every
core: nothing is pickled and no process starts. A triplet's projective refinement
(the tensors) is a Levenberg–Marquardt loop over small numpy arrays, Python and
per-call overhead that holds the GIL: two threads ran it no faster than one. Its jobs
run in forked processes instead (``processes=True``), where forking is safe
(:func:`can_fork`): the children inherit the jobs and the calibration's state with
the fork, and only their results are pickled back. The evaluation's many independent
calibrations use processes of their own (:mod:`..evaluation.runner`).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any

import cv2
from threadpoolctl import threadpool_limits
from tqdm import TMonitor, tqdm

from .errors import CalibrationError

MAX_WORKERS = 8


def default_workers() -> int:
    """One worker per available core, at most ``MAX_WORKERS``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS))


@contextmanager
def single_threaded_libraries() -> Iterator[None]:
    """BLAS, OpenMP and OpenCV each limited to one thread inside the block.

    The calibration multiplies many small matrices (24x24 camera blocks, 3x3 point
    blocks) and runs many small RANSACs; a library's own threads only add
    synchronisation to each call, and beside the worker threads of :func:`map_jobs`
    they oversubscribe the cores. Parallelism comes from :func:`map_jobs` instead.
    OpenCV's setting is restored afterwards.
    """
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(opencv_threads)


def map_jobs(
    function: Callable[[Any], Any],
    jobs: Sequence[Any],
    workers: int | None = None,
    description: str = "",
    *,
    progress: bool = False,
    processes: bool = False,
) -> list[Any]:
    """``[function(job) for job in jobs]``, in order, over ``workers`` threads, or with
    ``processes`` over forked worker processes where :func:`can_fork` (threads elsewhere).

    One worker, or a single job, runs in the calling thread. The processes inherit
    ``function`` and ``jobs`` (closures included) with the fork; each result is pickled
    back. On an exception (Ctrl-C included) the jobs not yet started are cancelled and
    the running ones finish (each is one triplet: milliseconds), then the exception
    propagates.

    Raises:
        CalibrationError: a worker process died (killed, or out of memory).
    """
    workers = default_workers() if workers is None else max(1, workers)
    bar = tqdm(total=len(jobs), desc=description, disable=not progress)
    try:
        if workers == 1 or len(jobs) <= 1:
            results = []
            for job in jobs:
                results.append(function(job))
                bar.update()
            return results
        if processes and can_fork():
            return _in_processes(function, jobs, min(workers, len(jobs)), bar)
        executor = ThreadPoolExecutor(min(workers, len(jobs)))
        futures = [executor.submit(function, job) for job in jobs]
        return _collect(executor, futures, bar)
    finally:
        bar.close()


def can_fork() -> bool:
    """Whether worker processes can be forked from here: on Linux, from the main thread
    of a process that runs no other thread of Python's (tqdm's sleeping monitor aside)
    and is not itself a daemonic worker (which may not have children).

    A child forked beside another running thread can deadlock on a lock that thread
    held; a Jupyter kernel, a Dask or pytest-xdist worker and a caller's own thread pool
    all run such threads, and get threads here instead.
    """
    if sys.platform != "linux" or multiprocessing.current_process().daemon:
        return False
    if threading.current_thread() is not threading.main_thread():
        return False
    return all(
        thread is threading.main_thread() or isinstance(thread, TMonitor)
        for thread in threading.enumerate()
    )


#: The function and jobs of the running :func:`_in_processes`, which its forked workers
#: inherit (so that only results cross between the processes).
_INHERITED: tuple[Callable[[Any], Any], Sequence[Any]] | None = None


def _in_processes(
    function: Callable[[Any], Any], jobs: Sequence[Any], workers: int, bar: tqdm
) -> list[Any]:
    """:func:`map_jobs` over ``workers`` forked processes (see there)."""
    global _INHERITED
    _INHERITED = (function, jobs)
    try:
        executor = ProcessPoolExecutor(
            workers, mp_context=multiprocessing.get_context("fork"), initializer=_in_worker
        )
        futures = [executor.submit(_inherited_job, index) for index in range(len(jobs))]
        try:
            return _collect(executor, futures, bar)
        except BrokenProcessPool as error:
            raise CalibrationError(
                f"a worker process died ({error}); with --workers 1 the work stays in this process"
            ) from None
    finally:
        _INHERITED = None


def _collect(executor: Executor, futures: list[Any], bar: tqdm) -> list[Any]:
    """The futures' results in order; the executor shut down, the jobs not yet started
    cancelled (on an exception as well)."""
    try:
        results = []
        for future in futures:
            results.append(future.result())
            bar.update()
        return results
    finally:
        executor.shutdown(wait=True, cancel_futures=True)


def _in_worker() -> None:
    """A forked worker's set-up: the signals that end a run are the parent's to handle
    (it cancels what has not started and waits for the running jobs, milliseconds); the
    worker ends when the parent shuts the pool down."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)


def _inherited_job(index: int) -> Any:
    """Job ``index`` of the :func:`_in_processes` the worker was forked from."""
    assert _INHERITED is not None
    function, jobs = _INHERITED
    return function(jobs[index])
