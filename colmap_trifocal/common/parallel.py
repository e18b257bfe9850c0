"""Order-preserving map over worker threads or forked processes, with a progress bar;
BLAS kept single-threaded.

The lens search's and the diagnosis's jobs spend their time in OpenCV, which releases
the GIL, so threads use every core: nothing is pickled and no process starts. A
triplet's projective refinement (the tensors) is a Levenberg–Marquardt loop over small
numpy arrays, Python and per-call overhead that holds the GIL: two threads ran it no
faster than one. Its jobs run in forked processes instead (``processes=True``), where
forking is safe (:func:`can_fork`): the children inherit the jobs and the
calibration's state with the fork, and only their results are pickled back. So do the
focal search's (its calibrated hypotheses wrap OpenCV's RANSACs in numpy that holds
the GIL), and the other per-triplet numpy jobs from ``MIN_FORKED_JOBS`` triplets on
(the polish's and the lens stage's projective refits, calibrated cameras and Schur
complements; the plane parallax that weighs candidate triplets). The evaluation's many
independent calibrations use processes of their own (:mod:`..evaluation.runner`).
"""

from __future__ import annotations

import logging
import logging.handlers
import multiprocessing
import os
import queue
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import cv2
from threadpoolctl import threadpool_limits
from tqdm import TMonitor, tqdm

from .children import die_with_parent
from .errors import TERMINATING_SIGNALS, CalibrationError
from .log import logger

MAX_WORKERS = 8
#: Jobs from which a call of per-triplet numpy work that holds the GIL (a few
#: milliseconds a triplet: the polish's projective refits, calibrated cameras and Schur
#: complements, the tracks' plane parallax) goes to forked processes (threads below).
#: A fork costs 1–3 ms, and the copy-on-write faults it leaves the caller 0.01–0.03 s
#: more; from 10 triplets on, the half another core takes saves more than that
#: (docs/accuracy.md, thirty-first session).
MIN_FORKED_JOBS = 10
#: What a caller hears of a worker process that died (killed, out of memory).
WORKER_DIED = (
    "a worker process died; with one worker (--workers 1, workers=1) all the work stays "
    "in this process"
)


def default_workers() -> int:
    """One worker per available core, at most ``MAX_WORKERS``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS))


def worker_count(workers: int | None) -> int:
    """The workers asked for as a count: None is one per core (:func:`default_workers`)."""
    return default_workers() if workers is None else max(1, workers)


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
    ``processes`` over the calling thread and ``workers - 1`` forked processes where
    :func:`can_fork` (threads elsewhere).

    One worker, or a single job, runs in the calling thread. The processes inherit
    ``function`` and ``jobs`` (closures included) with the fork; their results are
    pickled back; a worker process that has sent them exits on its own, unwaited for
    (:func:`_released`). On an exception (Ctrl-C included) the jobs not yet started are
    cancelled, running threads finish their job (each is one triplet: milliseconds) and
    worker processes are ended; then the exception propagates.

    Raises:
        CalibrationError: a worker process died (killed, or out of memory).
    """
    workers = worker_count(workers)
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


def _in_processes(
    function: Callable[[Any], Any], jobs: Sequence[Any], workers: int, bar: tqdm
) -> list[Any]:
    """:func:`map_jobs` over the calling thread and ``workers - 1`` forked processes.

    Each takes the next job from a shared counter until none is left (a heavy triplet
    delays no other); a child keeps its results and sends them when it runs out of jobs
    (sent as they came, they would fill the pipe while the caller is busy with a job).
    An exception in any job stops the others from taking more, and is raised here.
    """
    taken = multiprocessing.get_context("fork").Value("q", 0)
    children = []
    answered = 0  # children[:answered] have sent their one message
    try:
        for _ in range(workers - 1):
            children.append(_forked(_take_jobs, function, jobs, taken))
        results: list[Any] = [None] * len(jobs)
        try:
            for index, value in _take_jobs_here(function, jobs, taken):
                results[index] = value
                bar.update()
        except BaseException:
            _take_none(taken, len(jobs))
            raise
        for _child, receiving in children:
            try:
                done, records, error = receiving.recv()
            except EOFError:
                raise CalibrationError(WORKER_DIED) from None
            answered += 1
            _emit(records)
            for index, value in done or ():
                results[index] = value
                bar.update()
            if error is not None:
                raise error
        return results
    finally:
        for position, (child, receiving) in enumerate(children):
            (_released if position < answered else _ended)(child, receiving)


def _forked(target: Callable[..., None], *args: Any) -> tuple[Any, Any]:
    """A started daemonic child forked to run ``target(*args, sending)``, and the end of
    the pipe it sends its one message on."""
    context = multiprocessing.get_context("fork")
    receiving, sending = context.Pipe(duplex=False)
    child = context.Process(target=target, args=(*args, sending), daemon=True)
    # Held back across the fork: a signal to the process group between the fork and the
    # child's own set-up (:func:`_in_worker`) would otherwise run the parent's handler in
    # the child, whose KeyboardInterrupt multiprocessing reports on stderr.
    held = signal.pthread_sigmask(signal.SIG_BLOCK, TERMINATING_SIGNALS)
    try:
        child.start()
    finally:
        try:  # a signal held back meanwhile: its handler runs (and raises) in this call
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
        except BaseException:
            sending.close()
            if child.pid is not None:
                _ended(child, receiving)  # no caller will end it
            raise
    sending.close()
    return child, receiving


def _ended(child: Any, receiving: Any) -> None:
    """``child`` killed if still running, joined, and its pipe's end closed."""
    if child.is_alive():
        child.kill()
    child.join()
    receiving.close()


def _released(child: Any, receiving: Any) -> None:
    """A ``child`` that has sent its one message let go: its pipe's end closed, the child
    reaped if it has already exited, else left to exit on its own. It is not waited
    for: its exit (unmapping its copy of the caller's memory) took 8 ms of every forked
    call here, on the caller's path (docs/accuracy.md, forty-ninth session).
    ``multiprocessing`` reaps it at the next fork, or at the caller's exit (a daemon)."""
    receiving.close()
    child.join(timeout=0)


def _take_jobs_here(
    function: Callable[[Any], Any], jobs: Sequence[Any], taken: Any
) -> Iterator[tuple[int, Any]]:
    """(index, result) of each job taken from the shared counter ``taken``, in turn."""
    while True:
        with taken.get_lock():
            index = taken.value
            taken.value = index + 1
        if index >= len(jobs):
            return
        yield index, function(jobs[index])


def _take_none(taken: Any, count: int) -> None:
    """No worker takes another of the ``count`` jobs."""
    with taken.get_lock():
        taken.value = count


def _take_jobs(
    function: Callable[[Any], Any], jobs: Sequence[Any], taken: Any, sending: Any
) -> None:
    """A forked worker of :func:`_in_processes`: jobs until none is left, then its
    results, its log records and the exception that stopped it (None), on ``sending``."""
    records = _in_worker()
    done: list[tuple[int, Any]] = []
    error: BaseException | None = None
    try:
        done.extend(_take_jobs_here(function, jobs, taken))
    except BaseException as raised:  # noqa: BLE001 - the caller raises it
        _take_none(taken, len(jobs))
        error = raised
    _send(sending, (done, _drained(records), error))


def _send(sending: Any, message: tuple[Any, ...]) -> None:
    """A worker's last act: ``message`` on ``sending`` (a pipe's end, closed after); where
    it cannot be pickled, a message with no results and the error saying so.

    From here the worker only exits, unwaited for (:func:`_released`): the signals that
    end a run take their default action in it again (it ends, silently), so that the
    caller's own exit, which ends its daemonic children with SIGTERM and joins them,
    cannot wait on one stuck in its exit. They take it before the message goes, held
    back until it has gone: once the caller has the message it may exit at once, and a
    SIGTERM that came while the worker still ignored it would be lost (CI run 103 waited
    on such a worker); held back, it is pending, and ends the worker when let through."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, TERMINATING_SIGNALS)
    try:
        for signum in TERMINATING_SIGNALS:
            signal.signal(signum, signal.SIG_DFL)
        try:
            sending.send(message)
        except Exception as unsent:  # noqa: BLE001 - unpicklable: say so instead
            sending.send(
                (*(None for _ in message[:-1]), RuntimeError(f"not sent back: {unsent!r}"))
            )
        sending.close()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def _in_worker() -> queue.SimpleQueue[logging.LogRecord]:
    """A forked worker's set-up; the queue its log records (the package logger's, its
    level as in the parent) go to, for the parent to emit.

    The signals that end a run are the parent's to handle (it stops the workers); the
    worker ends when its work is done, when the parent ends it, or with the parent
    (:func:`.children.die_with_parent`): a parent killed without its clean-up (SIGKILL,
    or a SIGTERM it has no handler for) cannot end it, and a worker left behind would
    finish its jobs, then wait forever to write results to a pipe nobody reads. Its
    records are the parent's to emit, through the parent's handlers (a test's capture,
    the command line's stderr), and only where its result is used (:class:`Beside`).
    """
    parent = multiprocessing.parent_process()
    if parent is not None and parent.pid is not None:
        die_with_parent(parent.pid)
    for signum in TERMINATING_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)  # discards one already held back
    signal.pthread_sigmask(signal.SIG_UNBLOCK, TERMINATING_SIGNALS)  # held by _forked
    records: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    logger.handlers = [logging.handlers.QueueHandler(records)]
    logger.propagate = False
    return records


def _drained(records: queue.SimpleQueue[logging.LogRecord]) -> list[logging.LogRecord]:
    """What ``records`` holds, in order."""
    return [records.get_nowait() for _ in range(records.qsize())]


def _emit(records: list[logging.LogRecord] | None) -> None:
    """A worker's log records, emitted here through the package logger's handlers."""
    for record in records or ():
        logger.handle(record)


class Beside:
    """``function()`` computed beside the caller's own work: in a forked process where
    there are ``workers`` (None: one per core) beside the caller and :func:`can_fork`
    (started at once), else in the caller when :meth:`result` asks for it. A context
    manager: leaving it ends a process whose result was not asked for.

    The child inherits ``function`` (a closure included) with the fork, ignores the
    signals that end a run (the caller's to handle), and sends back its result or its
    exception, pickled.
    """

    def __init__(self, function: Callable[[], Any], *, workers: int | None = None):
        self._function = function
        self._process: Any = None
        self._connection: Any = None
        if worker_count(workers) > 1 and can_fork():
            self._process, self._connection = _forked(_send_result, function)

    def result(self) -> Any:
        """The function's value (its exception raised here).

        Raises:
            CalibrationError: the process died before it sent its result.
        """
        if self._process is None:
            return self._function()
        try:
            value, records, error = self._connection.recv()
        except BaseException as raised:
            self.close()
            if isinstance(raised, EOFError):
                raise CalibrationError(WORKER_DIED) from None
            raise
        self._let_go(_released)
        _emit(records)
        if error is not None:
            raise error
        return value

    def close(self) -> None:
        """End the process (if still running) and release its pipe."""
        if self._process is None:
            return
        self._let_go(_ended)

    def _let_go(self, end: Callable[[Any, Any], None]) -> None:
        """The process let go by ``end`` (:func:`_ended` or :func:`_released`), and the
        function no longer to be asked for."""
        end(self._process, self._connection)
        self._process = None
        self._function = _closed

    def __enter__(self) -> Beside:
        return self

    def __exit__(self, *exception: object) -> None:
        self.close()


def _closed() -> Any:
    raise RuntimeError("Beside: the process was closed before its result was asked for")


def _send_result(function: Callable[[], Any], sending: Any) -> None:
    """A :class:`Beside` child: ``function()``, its log records and its exception
    (None), on ``sending``."""
    records = _in_worker()
    value, error = None, None
    try:
        value = function()
    except BaseException as raised:  # noqa: BLE001 - the caller raises it
        error = raised
    _send(sending, (value, _drained(records), error))
