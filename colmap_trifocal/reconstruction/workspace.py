"""The ``run`` workspace: created, locked for one run at a time, earlier results replaced.

A run holds an exclusive ``flock`` on :data:`LOCK_NAME` in the workspace from before it
touches anything there until it ends; a second run on the same workspace finds the lock
taken and stops with a :class:`CalibrationError` before changing anything. The lock is an
open file description's (``flock``), so it binds other processes and other opens in this
process alike, and the kernel releases it when the process ends however it ends. The lock
file is removed when the run ends; one left by a killed run is reused and ignored when
deciding whether the workspace is empty.

A workspace this process cannot write to (no write permission, a read-only file system) is
refused in one line before COLMAP is asked to create its database there.
"""

from __future__ import annotations

import errno
import fcntl
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.files import can_create_in, missing_folders, remove_if_empty

#: What a run writes into the workspace (``--overwrite`` removes exactly these).
WORKSPACE_OUTPUTS = ("database.db", "sparse", "report.json")
#: The lock file of a run in progress.
LOCK_NAME = ".colmap-trifocal.lock"


def refuse_workspace_over_images(images: Path | None, workspace: Path) -> None:
    """CalibrationError where the workspace is the image folder (or a link to it), holds
    it, or lies inside it (real paths): a run writes ``database.db``, ``sparse/`` and
    ``report.json`` there, and ``--overwrite`` removes them first, which in the image
    folder, or in the COLMAP project that holds it, are the user's own."""
    if images is None:
        return
    real_images = Path(os.path.realpath(images))
    real_workspace = Path(os.path.realpath(workspace))
    if real_workspace == real_images:
        relation = "is the image folder"
    elif real_images in real_workspace.parents:
        relation = "is inside the image folder"
    elif real_workspace in real_images.parents:
        relation = "holds the image folder"
    else:
        return
    raise CalibrationError(
        f"WORKSPACE {workspace} {relation} (IMAGES {images}): refusing to write the run's "
        "database.db, sparse/ and report.json there (use a new folder for WORKSPACE)"
    )


@contextmanager
def open_workspace(workspace: Path, *, overwrite: bool) -> Iterator[Path]:
    """Create and lock ``workspace``, then :func:`prepare_workspace` it; unlock at the end.

    Raises:
        CalibrationError: the workspace is not a folder, cannot be written, is in use by
            another run, or holds other content without ``overwrite``.
    """
    workspace = Path(workspace)
    if workspace.exists() and not workspace.is_dir():
        raise CalibrationError(f"workspace is not a folder: {workspace}")
    created = missing_folders(workspace)
    workspace.mkdir(parents=True, exist_ok=True)
    try:
        if not can_create_in(workspace):
            raise CalibrationError(f"cannot write to workspace {workspace}: permission denied")
        with workspace_lock(workspace):
            prepare_workspace(workspace, overwrite=overwrite)
            yield workspace
    except BaseException:
        remove_if_empty(created)  # a refused run leaves no empty workspace behind
        raise


@contextmanager
def workspace_lock(workspace: Path) -> Iterator[None]:
    """Hold the workspace's lock for the block (see the module docstring).

    Raises:
        CalibrationError: another run holds it, or the lock file cannot be created.
    """
    path = Path(workspace) / LOCK_NAME
    fd = _acquire(path)
    try:
        yield
    finally:
        try:
            os.unlink(path)  # while still locked: a waiting opener then sees it gone
        except OSError:
            pass
        os.close(fd)


def _acquire(path: Path) -> int:
    """An open descriptor of ``path`` holding its exclusive lock.

    The holder removes the file before unlocking; a process that opened the old file
    and locked it after that finds its descriptor no longer at ``path`` and tries again.
    """
    workspace = path.parent
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise CalibrationError(
                f"cannot write to workspace {workspace}: {exc.strerror or exc}"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise CalibrationError(
                    f"workspace {workspace} is in use by another colmap-trifocal run "
                    f"(it holds {LOCK_NAME}); wait for it or use another WORKSPACE"
                ) from None
            raise CalibrationError(
                f"cannot lock workspace {workspace}: {exc.strerror or exc}"
            ) from None
        opened = os.fstat(fd)
        try:
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        if current is not None and (current.st_dev, current.st_ino) == (
            opened.st_dev,
            opened.st_ino,
        ):
            return fd
        os.close(fd)


def prepare_workspace(workspace: Path, *, overwrite: bool) -> None:
    """Refuse a workspace with other content unless ``overwrite``; then remove old outputs.

    The lock file does not count as content. With ``overwrite`` only this tool's outputs
    are removed (:data:`WORKSPACE_OUTPUTS`); other files are left alone. Call it with the
    workspace locked.
    """
    content = [p for p in workspace.iterdir() if p.name != LOCK_NAME]
    if not content:
        return
    if not overwrite:
        raise CalibrationError(
            f"workspace {workspace} is not empty (use --overwrite to replace its results)"
        )
    for name in WORKSPACE_OUTPUTS:
        target = workspace / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
