"""Run independent evaluation tasks on local cores or on an existing Dask cluster."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import pycolmap
from tqdm import tqdm

from ..common.errors import CalibrationError
from ..common.parallel import default_workers


def run_tasks(
    function: Callable[[Any], Any],
    tasks: Sequence[Any],
    workers: int | None = None,
    dask_address: str | None = None,
    description: str = "",
    progress: bool = False,
) -> list[Any]:
    """``[function(task) for task in tasks]`` in order, with a progress bar.

    Locally: ``workers`` processes (default one per core), started with
    ``forkserver`` rather than forked: the tasks call pycolmap's multi-threaded
    code, which can deadlock or abort in a child forked from a process that has
    already run it (the workers die and the pool hangs). With
    ``dask_address`` (``tcp://host:8786``) the tasks go to that Dask scheduler; its
    workers need this package installed. ``function`` must be module-level.
    COLMAP's log level of this process is applied in every worker.
    """
    level = int(pycolmap.logging.minloglevel)
    if dask_address is not None:
        return _run_on_dask(function, tasks, dask_address, description, progress, level)
    workers = default_workers() if workers is None else max(1, workers)
    bar = tqdm(total=len(tasks), desc=description, disable=not progress)
    try:
        if workers == 1 or len(tasks) <= 1:
            results = []
            for task in tasks:
                results.append(function(task))
                bar.update()
            return results
        context = multiprocessing.get_context(
            "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
        )
        with ProcessPoolExecutor(
            min(workers, len(tasks)),
            mp_context=context,
            initializer=_set_log_level,
            initargs=(level,),
        ) as pool:
            results = []
            try:
                for result in pool.map(function, tasks):
                    results.append(result)
                    bar.update()
            except BrokenProcessPool:
                raise CalibrationError(
                    "an evaluation worker process died (out of memory or a crash in pycolmap)"
                ) from None
            return results
    finally:
        bar.close()


def _set_log_level(level: int) -> None:
    pycolmap.logging.minloglevel = level


class _WithLogLevel:
    """``function`` run with COLMAP's log level set first (Dask workers start at 0)."""

    def __init__(self, function: Callable[[Any], Any], level: int):
        self.function, self.level = function, level

    def __call__(self, task: Any) -> Any:
        _set_log_level(self.level)
        return self.function(task)


def _run_on_dask(
    function: Callable[[Any], Any],
    tasks: Sequence[Any],
    address: str,
    description: str,
    progress: bool,
    level: int,
) -> list[Any]:
    from distributed import Client, as_completed

    try:
        client = Client(address, timeout="10s")
    except OSError as exc:
        raise CalibrationError(f"cannot connect to the Dask scheduler {address}: {exc}") from None
    try:
        futures = client.map(_WithLogLevel(function, level), tasks, pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        results: list[Any] = [None] * len(tasks)
        with tqdm(total=len(tasks), desc=description, disable=not progress) as bar:
            for future in as_completed(futures):
                results[index[future.key]] = future.result()
                bar.update()
        return results
    finally:
        client.close()
