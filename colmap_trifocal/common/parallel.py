"""Order-preserving map over worker threads, with a progress bar; BLAS kept single-threaded.

The calibration's parallel stages (the focal search, the tensors) spend their time in
OpenCV and in numpy's array operations, which release the GIL, so threads use every
core without forking: nothing is pickled, no process starts, and no child is forked
from a process in which pycolmap has already started threads (such children can
deadlock). The evaluation's many independent calibrations use processes instead
(:mod:`..evaluation.runner`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import cv2
from threadpoolctl import threadpool_limits
from tqdm import tqdm

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
) -> list[Any]:
    """``[function(job) for job in jobs]``, in order, over ``workers`` threads.

    One worker, or a single job, runs in the calling thread. On an exception (Ctrl-C
    included) the jobs not yet started are cancelled and the running ones finish
    (each is one triplet: milliseconds), then the exception propagates.
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
        executor = ThreadPoolExecutor(min(workers, len(jobs)))
        try:
            futures = [executor.submit(function, job) for job in jobs]
            results = []
            for future in futures:
                results.append(future.result())
                bar.update()
            return results
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
