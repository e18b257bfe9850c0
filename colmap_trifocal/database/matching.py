"""SIFT matching and two-view verification of image pairs, repeatable on any number of cores.

pycolmap's matcher on several threads of one process is not repeatable: now and then the
first pairs its threads take up together (two pairs that share an image) lose much of
their matches, a different share every time; on one thread it does not happen
(docs/reliability.md, "Determinism").

So each worker here is a process that matches its share of the pairs in one pycolmap call
on one thread, in its own copy of the database, whose matches and two-view geometries are
then copied back in pair order. A pair's result depends only on its two images and the
verification's seed, so the database is the one a single thread builds, whatever the
number of workers. In the copies each image is named by its id: COLMAP reads a pairs
file's lines as two names split at a space, so a name with a space matched nothing.

Each worker's share is one call, not many: a call builds the descriptor index of every
image it meets once, and a call per few pairs would build them again for every call. A
progress bar follows the pairs each worker has verified, read from its database while it
works (a pycolmap database is in WAL mode, so reading it does not hold up its writer).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path

import pycolmap
from tqdm import tqdm

from ..common.children import child_process
from ..common.errors import CalibrationError
from ..common.pycolmap_child import failure_reason
from .sqlite_files import copy_database

#: Fewest pairs a worker process is started for: below it, starting one costs more than
#: it saves.
PAIRS_PER_WORKER = 4
#: Seconds between two readings of the workers' progress.
POLL_S = 0.2

#: A worker: die with the parent, then ``match_share(**json)`` (its log on stderr).
_WORKER = """\
import json, sys
from colmap_trifocal.common.children import die_with_parent
die_with_parent(int(sys.argv[2]))
from colmap_trifocal.database.matching import match_share
match_share(**json.loads(sys.argv[1]))
"""


def worker_count(pairs: int, workers: int, database_bytes: int, free_bytes: int) -> int:
    """How many workers match ``pairs`` pairs: at most ``workers``, one per
    :data:`PAIRS_PER_WORKER` pairs, and no more copies of the database (one per worker)
    than fit in half the free space beside it; at least one."""
    copies = free_bytes // (2 * max(database_bytes, 1))
    return max(1, min(workers, math.ceil(pairs / PAIRS_PER_WORKER), copies))


def verification_options(seed: int | None) -> pycolmap.TwoViewGeometryOptions:
    """pycolmap's default two-view verification, its RANSAC seeded with ``seed`` (None:
    random)."""
    verification = pycolmap.TwoViewGeometryOptions()
    if seed is not None:
        verification.ransac.random_seed = seed
    return verification


def match_share(database: str, pairs_file: str, seed: int | None, minloglevel: int) -> None:
    """A worker's work: match and verify the image pairs listed by name in ``pairs_file``
    (one pair per line) in ``database``, in one pycolmap call on one thread.

    Always in a worker process, even the only one: the process that waits for it stays in
    Python, where a signal that ends it runs the clean-up (the copies)."""
    pycolmap.logging.minloglevel = minloglevel
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pairs_file
    pycolmap.match_image_pairs(
        database,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification_options(seed),
        device=pycolmap.Device.cpu,
    )


def match_pairs(
    database: Path,
    pairs: Sequence[tuple[int, int]],
    *,
    seed: int | None,
    workers: int,
    progress: bool = False,
) -> None:
    """Match and verify ``pairs`` of images of ``database``, which holds their features
    and no matches yet.

    Args:
        database: the COLMAP database, written in place.
        pairs: the image pairs (image ids), in the order of COLMAP's pair generator.
        seed: the verification's RANSAC seed (None: random).
        workers: most worker processes (each matches on one thread).
        progress: a bar of pairs verified on stderr.

    Raises:
        CalibrationError: a worker failed (a full disk, or the last line of its log).
    """
    if not pairs:
        return
    free = shutil.disk_usage(database.parent).free
    count = worker_count(len(pairs), workers, database.stat().st_size, free)
    with tempfile.TemporaryDirectory(dir=database.parent, prefix=".matching-") as tmp:
        bounds = [k * len(pairs) // count for k in range(count + 1)]
        shares = [list(pairs[start:end]) for start, end in zip(bounds, bounds[1:], strict=False)]
        files = [Path(tmp) / f"pairs-{k}.txt" for k in range(count)]
        copies = [Path(tmp) / f"worker-{k}.db" for k in range(count)]
        for share, file, copy in zip(shares, files, copies, strict=True):
            file.write_text("".join(f"{a} {b}\n" for a, b in share))
            copy_database(database, copy, temporary=True)
            _name_images_by_id(copy)
        _run_workers(database, copies, files, len(pairs), seed, Path(tmp), progress=progress)
        _copy_back(database, copies, shares)


def _name_images_by_id(database: Path) -> None:
    """Rename every image of ``database`` (a worker's copy) to its id."""
    with pycolmap.Database.open(str(database)) as db, pycolmap.DatabaseTransaction(db):
        for image in db.read_all_images():
            image.name = str(image.image_id)
            db.update_image(image)


def _run_workers(  # noqa: PLR0913 (the workers' files and settings)
    database: Path,
    targets: list[Path],
    files: list[Path],
    total: int,
    seed: int | None,
    tmp: Path,
    *,
    progress: bool,
) -> None:
    """One worker process per ``(target, file)``; wait for all, with a bar of the
    ``total`` pairs.

    The workers' COLMAP logs are kept in files to explain a failure, and passed on to
    stderr after they end where pycolmap's log level lets everything out."""
    minloglevel = int(pycolmap.logging.minloglevel)
    logs = [tmp / f"worker-{k}.log" for k in range(len(targets))]
    try:
        _wait_for_workers(
            database, targets, files, logs, total, seed, minloglevel, progress=progress
        )
    finally:
        if minloglevel == 0:
            for log in logs:
                with contextlib.suppress(OSError):
                    sys.stderr.write(log.read_text(encoding="utf-8", errors="replace"))


def _wait_for_workers(  # noqa: PLR0913 (the workers' files and settings)
    database: Path,
    targets: list[Path],
    files: list[Path],
    logs: list[Path],
    total: int,
    seed: int | None,
    minloglevel: int,
    *,
    progress: bool,
) -> None:
    """Start the workers of :func:`_run_workers`, and wait for them."""
    with ExitStack() as stack:
        bar = stack.enter_context(
            tqdm(total=total, desc="matching: image pairs", unit="pair", disable=not progress)
        )
        children, verified = [], [0] * len(targets)
        for target, file, log_path in zip(targets, files, logs, strict=True):
            arguments = {
                "database": str(target),
                "pairs_file": str(file),
                "seed": seed,
                "minloglevel": minloglevel,
            }
            log = stack.enter_context(log_path.open("wb"))
            command = [sys.executable, "-c", _WORKER, json.dumps(arguments), str(os.getpid())]
            children.append(
                stack.enter_context(
                    child_process(
                        command,
                        stdin=subprocess.DEVNULL,
                        stdout=subprocess.DEVNULL,
                        stderr=log,
                    )
                )
            )
        while True:
            statuses = [child.poll() for child in children]
            for log_path, status in zip(logs, statuses, strict=True):
                if status is not None and status != 0:
                    _raise_failure(database, log_path, status)
            if progress:
                verified = [_verified(t, last) for t, last in zip(targets, verified, strict=True)]
                bar.update(sum(verified) - bar.n)
            if all(status == 0 for status in statuses):
                bar.update(total - bar.n)
                return
            time.sleep(POLL_S)


def _verified(database: Path, last: int) -> int:
    """The pairs a worker has verified so far in ``database`` (``last``, the previous
    reading, where it cannot be read now)."""
    try:
        con = sqlite3.connect(f"{database.resolve().as_uri()}?mode=ro", uri=True, timeout=0)
        try:
            count = con.execute("SELECT count(*) FROM two_view_geometries").fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return last
    return max(last, int(count))


def _raise_failure(database: Path, log: Path, status: int) -> None:
    """Raise the CalibrationError of a worker matching pairs of ``database`` that ended
    with ``status``."""
    lines = log.read_bytes()[-(1 << 16) :].decode("utf-8", "replace").strip().splitlines()
    how = f"killed by signal {-status}" if status < 0 else f"exit status {status}"
    reason = failure_reason(database, lines)
    stopped = f"a worker stopped, {how}"
    raise CalibrationError(
        f"cannot match the image pairs of {database}: "
        + (stopped if reason == "?" else f"{reason} ({stopped})")
    )


def _copy_back(database: Path, copies: list[Path], shares: list[list[tuple[int, int]]]) -> None:
    """Write the matches and two-view geometries of each pair (image ids) of ``shares``
    from the workers' ``copies`` into ``database``, in pair order, empty ones included
    (pycolmap's ``read_all_matches`` leaves those out)."""
    with pycolmap.Database.open(str(database)) as db, pycolmap.DatabaseTransaction(db):
        for copy, share in zip(copies, shares, strict=True):
            with pycolmap.Database.open(str(copy)) as source:
                for pair in share:
                    if source.exists_matches(*pair):
                        db.write_matches(*pair, source.read_matches(*pair))
                    if source.exists_two_view_geometry(*pair):
                        db.write_two_view_geometry(*pair, source.read_two_view_geometry(*pair))
