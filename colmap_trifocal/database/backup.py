"""The backup a write makes of the user's database, under the write's lock.

A hidden temporary file, filled by SQLite's backup API through a second connection
(:func:`.sqlite_files.copy_open_database`: Python never opens the database file itself,
which would drop the process's POSIX locks on it), flushed to disk, then given the name
``<name>.bak`` (``.bak1``, ... if taken). A backup seen while the lock is held belongs to
a write that was killed and is removed (:mod:`.writing` orders these steps).
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.log import logger
from .sqlite_files import copy_open_database


@dataclass
class Backup:
    """The backup one write makes of ``database``.

    Attributes:
        database: the database backed up.
        temporary: the hidden file the copy is made in, ``.<name>.bak.XXXXXXXX.tmp``.
        identity: ``(st_dev, st_ino)`` of that file: every name it gets is this backup's.
        published: the name the complete copy was given (``<name>.bak``, ``.bak1``, ...).
    """

    database: Path
    temporary: Path | None = None
    identity: tuple[int, int] | None = None
    published: Path | None = None

    def remove(self) -> None:
        """Remove every name of this backup's file, and every temporary copy of the database.

        Called with the write lock held: no other write of the database is making a
        temporary copy, so all of them are this write's or left by one that did not finish.
        """
        pattern = re.compile(rf"{re.escape(self.database.name)}\.bak\d*")
        if self.identity is not None:
            for entry in os.scandir(self.database.parent):
                if pattern.fullmatch(entry.name) and _identity(Path(entry.path)) == self.identity:
                    _unlink(Path(entry.path))
        remove_temporaries(self.database)


def _unlink(path: Path) -> bool:
    """Remove the file at ``path`` if it is there; False (and a warning) if that fails."""
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:
        logger.warning("cannot remove %s: %s", path, exc.strerror or exc)
        return False
    return True


def _identity(path: Path) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of the file at ``path`` itself (a symlink is not followed)."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _temporaries(database: Path) -> list[Path]:
    """The temporary backup copies next to ``database``: ``.<name>.bak.XXXXXXXX.tmp``, the
    eight characters from :func:`tempfile.mkstemp` (letters, digits, ``_``)."""
    pattern = re.compile(rf"\.{re.escape(database.name)}\.bak\.[a-z0-9_]{{8}}\.tmp")
    return [
        Path(entry.path) for entry in os.scandir(database.parent) if pattern.fullmatch(entry.name)
    ]


def remove_temporaries(database: Path) -> list[Path]:
    """Remove the temporary backup copies of ``database`` (the caller holds its write lock,
    so no running write is making one); return them."""
    return [temporary for temporary in _temporaries(database) if _unlink(temporary)]


def back_up_locked(path: Path) -> Backup:
    """Back up the database at ``path`` to ``<name>.bak`` (``.bak1``, ... if taken) while
    the caller holds its write lock (``BEGIN IMMEDIATE`` on the caller's own connection).

    The returned backup's ``remove()`` takes it away again (call it before ROLLBACK).

    Raises:
        CalibrationError: the copy could not be made (nothing is left behind).
    """
    for stale in remove_temporaries(path):
        logger.info("removed %s: the copy of a backup that did not finish", stale)
    backup = Backup(path)
    try:
        make_backup(path, backup)
    except BaseException:
        backup.remove()
        raise
    return backup


def make_backup(path: Path, backup: Backup) -> None:
    """Copy the database at ``path`` to its backup: claim, copy and flush, publish.

    Raises:
        CalibrationError: the copy could not be made (no space, no permission, ...); the
            caller removes what was made.
    """
    try:
        _claim_backup_path(backup)
        assert backup.temporary is not None
        _copy_database(path, backup.temporary)
        _publish_backup(backup)
    except OSError as exc:
        raise CalibrationError(
            f"cannot back up the database, nothing written: {path} ({exc.strerror or exc})"
        ) from exc
    logger.info("backed up %s to %s", path, backup.published)


def _claim_backup_path(backup: Backup) -> None:
    """Create the empty hidden file ``.<name>.bak.XXXXXXXX.tmp`` for the copy (permissions
    as the umask gives a new file).

    The copy is made under this name and only renamed to ``<name>.bak`` by
    :func:`_publish_backup` once it is complete and on disk, so a ``.bak`` is never a
    partial copy, whatever ends the process.
    """
    database = backup.database
    fd, name = tempfile.mkstemp(dir=database.parent, prefix=f".{database.name}.bak.", suffix=".tmp")
    try:
        backup.temporary = Path(name)
        st = os.fstat(fd)
        backup.identity = st.st_dev, st.st_ino
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
    finally:
        os.close(fd)


def _copy_database(path: Path, target: Path) -> None:
    """Copy the database at ``path`` into the existing file ``target`` and flush it to disk.

    The caller holds the write lock, so nobody else can commit meanwhile; the copy is
    SQLite's backup API (:func:`.copy_open_database`), never Python's own reading of the
    file, whose closing would drop that lock. It holds the committed changes still in the
    ``-wal``, and the same rows as the file (its header's change counters differ).
    """
    copy_open_database(path, target)
    fd = os.open(target, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _publish_backup(backup: Backup) -> None:
    """Give the complete copy the first free name ``<name>.bak``, ``.bak1``, ...

    An existing backup is never overwritten: the name is taken with ``os.link``, which
    fails if it exists (a file system without hard links falls back to a check and a
    rename). The folder is flushed so that the name is on disk before the database
    changes.
    """
    database, temporary = backup.database, backup.temporary
    assert temporary is not None
    index = 0
    while True:
        candidate = database.with_name(f"{database.name}.bak{index or ''}")
        try:
            os.link(temporary, candidate)
        except FileExistsError:
            index += 1
            continue
        except OSError:  # no hard links here
            if candidate.exists():
                index += 1
                continue
            os.rename(temporary, candidate)
        else:
            temporary.unlink()
        backup.published = candidate
        _sync_folder(database.parent)
        return


def _sync_folder(folder: Path) -> None:
    """Flush a folder's entries (a new file name) to disk, where the system allows it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
