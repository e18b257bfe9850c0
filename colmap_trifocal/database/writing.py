"""Write calibrated intrinsics into the user's COLMAP database: backup, one transaction, check.

Order of events: take the write lock (``BEGIN IMMEDIATE``: no other connection can commit
from now on), remove backup copies that earlier writes left unfinished (a write makes one
only while it holds that lock, so one seen now belongs to a write that was killed), check
the cameras, copy the database to a hidden temporary file, flush it to disk and give it
the name ``<name>.bak`` (``.bak1``, ... if taken), UPDATE, COMMIT, read back on a fresh
connection. Until COMMIT
any error or interrupt (Ctrl-C, SIGTERM, SIGHUP) removes the backup and rolls back,
leaving the database byte-identical and no backup behind; COMMIT itself is the one step
during which these signals wait (:func:`_write_and_commit`).

The write is Python's ``sqlite3`` with SQL, not pycolmap's ``Database.update_camera``:
pycolmap's ``DatabaseTransaction`` ends with ``END TRANSACTION`` whatever happened in it (a
write interrupted half-way is committed, a failed COMMIT is only logged), opening the file
with pycolmap rewrites its header, and pycolmap's own SQLite does not see the write lock of
Python's ``sqlite3`` in the same process.

While the write connection is open, the file is never opened by Python itself (the
backup is SQLite's backup API through a second connection): closing any descriptor of a
file drops every POSIX lock the process holds on it, and another process's reader could
then checkpoint and delete the ``-wal`` the write commits into (SQLite's "How To Corrupt
An SQLite Database File", §2.2). The parameters are read back after COMMIT on a new
connection; where they differ, the write fails with ``error:``.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import stat
from contextlib import closing
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError, interrupts_deferred
from ..common.log import logger
from .backup import Backup, make_backup, remove_temporaries
from .cameras import CameraInfo
from .sqlite_files import (
    check_sqlite_file,
    check_tables,
    connect,
    database_error,
)


def check_writable(path: Path, *, backup: bool = True) -> None:
    """Raise :class:`CalibrationError` unless ``path`` is an SQLite file this process may change.

    Cheap (no database access): the CLI calls it before a long calibration so that a
    read-only database with ``--write`` is refused at once, not after minutes of work.
    Read-only means no write permission, or no write bit at all (even for root), or a
    folder in which the backup cannot be made; or no room for the write (and with
    ``backup``, the backup).
    """
    path = Path(path)
    check_sqlite_file(path)
    if not os.access(path, os.W_OK) or not path.stat().st_mode & (
        stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH
    ):
        raise CalibrationError(f"cannot write to read-only database: {path}")
    if not os.access(path.parent, os.W_OK):
        raise CalibrationError(f"cannot write next to the database (read-only directory): {path}")
    _check_room(path, backup=backup)


#: Room kept for the write itself beyond the backup (its journal, the changed pages).
WRITE_ROOM_BYTES = 256 * 1024


def _check_room(path: Path, *, backup: bool) -> None:
    """Refuse a write where the database's file system has no room for the write and, with
    ``backup``, the backup (the database and its ``-wal``): before, the calibration ran,
    then SQLite made ``-wal``/``-shm`` files it could not fill, and they were left next to
    the input."""
    size = 0
    if backup:
        size = path.stat().st_size
        try:  # another process's last close checkpoints and deletes it at any time
            size += Path(f"{path}-wal").stat().st_size
        except FileNotFoundError:
            pass
    needed = size + WRITE_ROOM_BYTES
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return  # unknown: the write says what fails
    if free < needed:
        what = "a backup of the database and the write" if backup else "the write"
        raise CalibrationError(
            f"no space for {what} ({free} bytes free, about {needed} needed): {path}"
        )


def write_intrinsics(
    path: Path,
    cameras: dict[int, CameraInfo],
    *,
    backup: bool = True,
    change_models: bool = False,
) -> Path | None:
    """Write the cameras' params into the COLMAP database at ``path`` (in place).

    Only the ``params`` column of the given cameras changes, and with ``change_models``
    their ``model`` (see the module docstring for the order of events and what an
    interrupt leaves behind).

    Args:
        path: COLMAP database.
        cameras: camera_id -> camera with the new params (same model and size as stored;
            with ``change_models`` the same size).
        backup: first copy the database to ``<name>.bak`` (or ``.bak1``, ``.bak2``, ... if
            taken; an existing backup is never overwritten).
        change_models: store each camera's model too: for a working copy this tool owns
            (``run`` maps a lens in the model that holds it); never a user's database.

    Returns:
        The backup's path, or None if no backup was made (``backup=False`` or no cameras).

    Raises:
        CalibrationError: missing/invalid/read-only/locked database, unknown camera, model
            or size mismatch, invalid params, no space for the backup, or failed
            verification.
        KeyboardInterrupt: interrupted; its message says so when the signal came during
            COMMIT (the database is then written and the backup kept).
    """
    path = Path(path)
    check_writable(path, backup=backup)
    if not cameras:
        logger.info("no cameras to write")
        return None
    _check_params(cameras)
    made = Backup(path) if backup else None
    try:
        with closing(connect(path, "mode=rw")) as con:
            check_tables(con, path)
            con.execute("BEGIN IMMEDIATE")
            _write_and_commit(con, path, cameras, made, change_models=change_models)
        # Read-write although it only reads: as the last connection it checkpoints and
        # removes the -wal and -shm files on closing, which a read-only one cannot.
        with closing(connect(path, "mode=rw")) as fresh:
            _verify_written(fresh, cameras, path, made)
    except sqlite3.Error as exc:
        raise database_error(exc, path, "write") from exc
    logger.info("wrote intrinsics of %d cameras to %s", len(cameras), path)
    return None if made is None else made.published


def _write_and_commit(
    con: sqlite3.Connection,
    path: Path,
    cameras: dict[int, CameraInfo],
    backup: Backup | None,
    *,
    change_models: bool = False,
) -> None:
    """Inside the caller's ``BEGIN IMMEDIATE``: check, back up, UPDATE, COMMIT.

    SIGINT, SIGTERM and SIGHUP wait while COMMIT runs, so that it is never split; one that
    arrived meanwhile is raised right after it. Whatever ends this before COMMIT has
    happened (``con.in_transaction`` still true, or any error) removes the backup and rolls
    back; an interrupt after COMMIT says that the database was written.
    """
    try:
        for stale in remove_temporaries(path):
            logger.info("removed %s: the copy of a backup that did not finish", stale)
        _check_cameras_match(con, cameras, path, same_model=not change_models)
        if backup is not None:
            make_backup(path, backup)
        _update_params(con, cameras, with_model=change_models)
        with interrupts_deferred():
            _commit(con)
    except BaseException as exc:
        if con.in_transaction or not isinstance(exc, KeyboardInterrupt):
            _undo(con, backup)
            raise
        kept = "no backup" if backup is None else f"backup: {backup.published}"
        written = f"after the new intrinsics were written to {path}; {kept}"
        raise KeyboardInterrupt(written) from None


def _undo(con: sqlite3.Connection, backup: Backup | None) -> None:
    """Remove this write's backup files, then ROLLBACK (the files go while the write lock
    still keeps other writers, and their temporary copies, away)."""
    if backup is not None:
        backup.remove()
    if con.in_transaction:
        con.execute("ROLLBACK")


def _commit(con: sqlite3.Connection) -> None:
    """COMMIT the caller's transaction."""
    con.execute("COMMIT")


# --------------------------------------------------------------------------- the cameras


def _params_blob(camera: CameraInfo) -> bytes:
    """COLMAP's ``cameras.params`` blob: the params as little-endian float64."""
    return np.ascontiguousarray(camera.params, dtype="<f8").tobytes()


def _check_params(cameras: dict[int, CameraInfo]) -> None:
    """Refuse to store params that no COLMAP camera can have (non-finite, focal length <= 0)."""
    for camera_id, cam in cameras.items():
        if not np.all(np.isfinite(cam.params)):
            raise CalibrationError(f"camera {camera_id}: refusing to write non-finite params")
        fx, fy, _, _ = cam.intrinsics
        if fx <= 0 or fy <= 0:
            raise CalibrationError(
                f"camera {camera_id}: refusing to write a focal length <= 0 "
                f"(fx = {fx:.6g}, fy = {fy:.6g})"
            )


def _check_cameras_match(
    con: sqlite3.Connection, cameras: dict[int, CameraInfo], path: Path, *, same_model: bool
) -> None:
    """Each camera must exist in the database with the same image size (and with
    ``same_model`` the same model)."""
    rows = {
        int(cid): (int(model), int(width), int(height))
        for cid, model, width, height in con.execute(
            "SELECT camera_id, model, width, height FROM cameras"
        )
    }
    for camera_id, cam in cameras.items():
        if camera_id != cam.camera_id:
            raise ValueError(f"cameras[{camera_id}] has camera_id {cam.camera_id}")
        if camera_id not in rows:
            raise CalibrationError(f"camera {camera_id} is not in the database: {path}")
        expected = (int(pycolmap.CameraModelId(cam.model)), cam.width, cam.height)
        if not same_model:
            expected = (rows[camera_id][0], *expected[1:])
        if rows[camera_id] != expected:
            raise CalibrationError(
                f"camera {camera_id} in the database differs in model or size from the "
                f"calibrated one: {path}"
            )


def _update_params(
    con: sqlite3.Connection, cameras: dict[int, CameraInfo], *, with_model: bool
) -> None:
    """The UPDATE of ``cameras.params`` (and ``model``: ``with_model``), inside the
    caller's transaction."""
    con.executemany(
        "UPDATE cameras SET params = ? WHERE camera_id = ?",
        [(_params_blob(cam), camera_id) for camera_id, cam in cameras.items()],
    )
    if with_model:
        con.executemany(
            "UPDATE cameras SET model = ? WHERE camera_id = ?",
            [(int(pycolmap.CameraModelId(c.model)), camera_id) for camera_id, c in cameras.items()],
        )


def _verify_written(
    con: sqlite3.Connection, cameras: dict[int, CameraInfo], path: Path, backup: Backup | None
) -> None:
    """Read the params back on a fresh connection, after COMMIT, and compare them bit for
    bit with what was written: a write that reports success must be on disk."""
    for camera_id, cam in cameras.items():
        row = con.execute(
            "SELECT params, model FROM cameras WHERE camera_id = ?", (camera_id,)
        ).fetchone()
        model = int(pycolmap.CameraModelId(cam.model))
        if row is None or bytes(row[0]) != _params_blob(cam) or int(row[1]) != model:
            kept = "" if backup is None else f"; backup: {backup.published}"
            raise CalibrationError(
                f"the database does not hold camera {camera_id}'s new parameters after the "
                f"write (another process changed it?): {path}{kept}"
            )
