"""Run independent tasks on local cores or on an existing Dask cluster.

:func:`run_tasks` returns every result in task order; :func:`completed_tasks` yields each
result as its task finishes (the evaluation's runs, ``calibrate``'s many databases).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import pycolmap
from tqdm import tqdm

from ..common.errors import CalibrationError
from ..common.extras import missing_extra
from ..common.parallel import worker_count

#: How long a Dask client waits for the scheduler before the run is refused.
DASK_CONNECT_TIMEOUT = "10s"


def run_tasks(
    function: Callable[[Any], Any],
    tasks: Sequence[Any],
    workers: int | None = None,
    dask_address: str | None = None,
    description: str = "",
    *,
    progress: bool = False,
) -> list[Any]:
    """``[function(task) for task in tasks]`` in order, with a progress bar.

    The tasks run as in :func:`completed_tasks`.
    """
    results: list[Any] = [None] * len(tasks)
    for index, result in completed_tasks(
        function, tasks, workers, dask_address, description, progress=progress
    ):
        results[index] = result
    return results


def completed_tasks(
    function: Callable[[Any], Any],
    tasks: Sequence[Any],
    workers: int | None = None,
    dask_address: str | None = None,
    description: str = "",
    *,
    progress: bool = False,
) -> Iterator[tuple[int, Any]]:
    """``(index, function(tasks[index]))`` for every task, as each finishes, with a bar.

    Locally: ``workers`` processes (default one per core), started with
    ``forkserver`` rather than forked: the tasks call pycolmap's multi-threaded
    code, which can deadlock or abort in a child forked from a process that has
    already run it (workers die and the pool hangs). One worker, or one task, runs
    in this process, in task order. With ``dask_address`` (``tcp://host:8786``) the
    tasks go to that Dask scheduler; its workers need this package installed and see
    the paths the tasks name. ``function`` must be module-level (picklable), and so
    must the tasks and results. COLMAP's log level of this process is applied in
    every worker. An exception of a task propagates; closing the iterator early
    cancels the tasks not yet finished.

    Raises:
        CalibrationError: a local worker process died, or the Dask scheduler cannot
            be reached within :data:`DASK_CONNECT_TIMEOUT`.
    """
    level = int(pycolmap.logging.minloglevel)
    bar = tqdm(total=len(tasks), desc=description, disable=not progress)
    try:
        if dask_address is not None:
            done = _on_dask(function, tasks, dask_address, level)
        else:
            workers = worker_count(workers)
            if workers == 1 or len(tasks) <= 1:
                done = ((i, function(task)) for i, task in enumerate(tasks))
            else:
                done = _on_processes(function, tasks, workers, level)
        for index, result in done:
            bar.update()
            yield index, result
    finally:
        bar.close()


def _on_processes(
    function: Callable[[Any], Any], tasks: Sequence[Any], workers: int, level: int
) -> Iterator[tuple[int, Any]]:
    context = multiprocessing.get_context(
        "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    )
    with ProcessPoolExecutor(
        min(workers, len(tasks)), mp_context=context, initializer=_set_log_level, initargs=(level,)
    ) as pool:
        futures = {pool.submit(function, task): i for i, task in enumerate(tasks)}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BrokenProcessPool:
            raise CalibrationError(
                "an evaluation worker process died (out of memory or a crash in pycolmap)"
            ) from None
        finally:
            for future in futures:
                future.cancel()


def _set_log_level(level: int) -> None:
    pycolmap.logging.minloglevel = level


class _WithLogLevel:
    """``function`` run with COLMAP's log level set first (Dask workers start at 0)."""

    def __init__(self, function: Callable[[Any], Any], level: int):
        self.function, self.level = function, level

    def __call__(self, task: Any) -> Any:
        _set_log_level(self.level)
        return self.function(task)


def _on_dask(
    function: Callable[[Any], Any], tasks: Sequence[Any], address: str, level: int
) -> Iterator[tuple[int, Any]]:
    try:
        from distributed import Client, as_completed
    except ModuleNotFoundError as exc:
        raise missing_extra("distributed", "--dask") from exc

    try:
        client = Client(address, timeout=DASK_CONNECT_TIMEOUT)
    except OSError as exc:
        raise CalibrationError(f"cannot connect to the Dask scheduler {address}: {exc}") from None
    try:
        futures = client.map(_WithLogLevel(function, level), tasks, pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        for future in as_completed(futures):
            yield index[future.key], future.result()
    finally:
        client.close()
