"""The SQLite file of a COLMAP database: checks, connections, errors, and the one copy of it.

Everything that opens the user's database with Python's ``sqlite3`` goes through here, so
that a lock held elsewhere waits ``_LOCK_TIMEOUT_S`` seconds everywhere, every SQLite error
becomes the same one-line :class:`CalibrationError` (classified by SQLite's error code), and
the user's file is copied one way, SQLite's backup API: :func:`copy_database` for the
snapshot that is read and the copy ``run`` works on, :func:`copy_open_database` for the
backup a write makes while it holds the write lock (see :mod:`.writing`).

pycolmap is never pointed at the user's file: ``pycolmap.Database.open`` writes to an
existing database (schema set-up rewrites the header even when nothing else changes), and
pycolmap links its own SQLite, whose POSIX locks do not see those of Python's ``sqlite3``
in the same process.
"""

from __future__ import annotations

import shlex
import sqlite3
import tempfile
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.log import logger

#: Tables every COLMAP database has.
REQUIRED_TABLES = ("cameras", "images", "keypoints", "two_view_geometries")

_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER_SIZE = 100
#: Seconds a connection waits for a lock held by another process before giving up.
_LOCK_TIMEOUT_S = 5.0


# --------------------------------------------------------------------------- the file


def check_sqlite_file(path: Path) -> bytes:
    """Check that ``path`` is a regular, readable SQLite file; return its 100-byte header."""
    if not path.exists():
        raise CalibrationError(f"database not found: {path}")
    if path.is_dir():
        raise CalibrationError(f"database path is a directory: {path}")
    if not path.is_file():
        raise CalibrationError(f"database path is not a regular file: {path}")
    try:
        with path.open("rb") as fh:
            header = fh.read(_HEADER_SIZE)
    except OSError as exc:
        raise CalibrationError(f"cannot read database: {path} ({exc.strerror})") from exc
    if len(header) < _HEADER_SIZE or not header.startswith(_SQLITE_MAGIC):
        raise CalibrationError(f"not an SQLite database: {path}")
    return header


def sidecar(path: Path, suffix: str) -> Path:
    """SQLite's companion file of the database at ``path``, e.g. ``<path>-wal``."""
    return path.with_name(path.name + suffix)


def check_tables(con: sqlite3.Connection, path: Path, schema: str = "main") -> set[str]:
    """The table names of the connected database ``schema``; raise unless COLMAP's are there."""
    names = {
        row[0] for row in con.execute(f"SELECT name FROM {schema}.sqlite_master WHERE type='table'")
    }
    missing = [table for table in REQUIRED_TABLES if table not in names]
    if missing:
        raise CalibrationError(f"not a COLMAP database (no table {', '.join(missing)}): {path}")
    return names


def connect(path: Path, query: str) -> sqlite3.Connection:
    """A connection to the database at ``path`` opened with the URI parameters ``query``
    (``mode=ro``, ``mode=rw``, ...): autocommit (transactions are explicit), and waiting
    up to ``_LOCK_TIMEOUT_S`` for another process's lock."""
    return sqlite3.connect(
        _uri(path, query), uri=True, timeout=_LOCK_TIMEOUT_S, isolation_level=None
    )


def _uri(path: Path, query: str) -> str:
    return f"{path.resolve().as_uri()}?{query}"


# --------------------------------------------------------------------------- errors


def database_error(
    exc: Exception,
    path: Path,
    action: str = "read",
    copy_folder: Path | None = None,
    *,
    temporary: bool = False,
) -> CalibrationError:
    """The one-line user error for an error SQLite or pycolmap raised on the database at ``path``.

    SQLite errors are told apart by their error code (``sqlite_errorcode``): busy or
    locked, a hot rollback journal that a read-only connection may not roll back, a full
    disk, an I/O error; any other code reads as a truncated or corrupt file. pycolmap
    raises ``RuntimeError`` (``ValueError``, ``MemoryError``) whose last line says what
    failed.

    Args:
        exc: the exception raised.
        path: the user's database.
        action: what was being done to it, as in "cannot read database".
        copy_folder: the folder a copy of the database was being written to; a full disk
            or an I/O error is then reported as a failed copy into it.
        temporary: the copy is this tool's temporary one: a full temporary folder
            (``TMPDIR``) is then named as such, with the way around it.
    """
    if not isinstance(exc, sqlite3.Error):
        message = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
        return CalibrationError(f"cannot {action} COLMAP database {path}: {message}")
    text = (str(exc).splitlines() or [type(exc).__name__])[0]
    code = getattr(exc, "sqlite_errorcode", None)
    primary = None if code is None else code & 0xFF
    if primary in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED):
        return CalibrationError(f"database is locked by another process: {path}")
    if code == sqlite3.SQLITE_READONLY_ROLLBACK:
        return CalibrationError(
            f"cannot {action} database: it has a hot rollback journal "
            f"{sidecar(path, '-journal')} (a process was killed while writing it); open it "
            f"once with write access, e.g. sqlite3 {shlex.quote(str(path))} "
            f"'PRAGMA quick_check', so that SQLite rolls that change back: {path} ({text})"
        )
    if primary in (sqlite3.SQLITE_FULL, sqlite3.SQLITE_IOERR):
        reason = "no space left on the device" if primary == sqlite3.SQLITE_FULL else text
        if copy_folder is None:
            return CalibrationError(f"cannot {action} database: {reason}: {path}")
        temporary_root = tempfile.gettempdir()
        if temporary and Path(temporary_root).resolve() in copy_folder.resolve().parents:
            return CalibrationError(
                f"cannot copy the database to the temporary folder {temporary_root} "
                f"({reason}; is it full? set TMPDIR to another folder): {path}"
            )
        return CalibrationError(f"cannot copy the database to {copy_folder} ({reason}): {path}")
    return CalibrationError(f"cannot {action} database (truncated or corrupt?): {path} ({text})")


# --------------------------------------------------------------------------- the copy


def copy_database(
    path: Path,
    target: Path,
    without_blobs: frozenset[str] = frozenset(),
    *,
    temporary: bool = False,
) -> None:
    """Copy the COLMAP database at ``path`` into ``target`` (a new or empty file).

    The copy is one read transaction, so it is consistent, and it holds every committed
    change, those still in the ``-wal`` file included. ``path`` is opened read-only. A
    WAL database without a ``-wal`` file (the main file then holds the whole database) is
    opened as immutable, which creates no ``-wal``/``-shm`` files next to it; that copy is
    kept only if the file did not change while it was made, else it is made again through
    a locking read-only connection.

    Args:
        path: the database.
        target: the copy; written without a journal (a partial copy is the caller's to
            remove).
        without_blobs: tables whose BLOB columns the copy leaves empty (their rows are
            kept, with their sizes). Without any, the copy is SQLite's backup API, page by
            page; with some, every table and index is created with the source's schema and
            filled table by table.
        temporary: ``target`` is this tool's temporary copy (see :func:`database_error`).

    Raises:
        CalibrationError: not an SQLite or COLMAP database, locked, corrupt, or no room
            for the copy.
    """
    path, target = Path(path), Path(target)
    header = check_sqlite_file(path)
    wal_mode = header[18] == 2 and header[19] == 2
    try:
        if wal_mode and not sidecar(path, "-wal").exists():
            before = _stat_key(path)
            _copy(_uri(path, "mode=ro&immutable=1"), target, without_blobs, path)
            if _stat_key(path) == before:
                return
            logger.debug("database changed while copying; copying again with locking: %s", path)
            target.write_bytes(b"")
        _copy(_uri(path, "mode=ro"), target, without_blobs, path)
    except sqlite3.Error as exc:
        raise database_error(
            exc, path, "copy", copy_folder=target.parent, temporary=temporary
        ) from exc


def copy_open_database(path: Path, target: Path) -> None:
    """Copy the database at ``path`` into ``target`` while this process holds a connection
    to it (the write lock of :mod:`.writing`).

    SQLite's backup API through a second, read-only connection of the same SQLite library:
    the file is never opened by Python itself, because closing any descriptor of a file
    drops every POSIX lock the process holds on it (SQLite's "How To Corrupt An SQLite
    Database File", §2.2), and with the lock gone another process may checkpoint and
    delete the ``-wal`` the write is about to commit into. The copy holds every committed
    change, those still in the ``-wal`` included. (The write connection itself cannot be
    the source: SQLite's backup refuses a source in a write transaction.)

    Raises:
        CalibrationError: locked, corrupt, or no room for the copy.
    """
    try:
        _copy(_uri(path, "mode=ro"), target, frozenset(), path)
    except sqlite3.Error as exc:
        raise database_error(exc, path, "copy", copy_folder=target.parent) from exc


def _stat_key(path: Path) -> tuple[int, int, int]:
    st = path.stat()
    return st.st_ino, st.st_size, st.st_mtime_ns


def _copy(source: str, target: Path, without_blobs: frozenset[str], path: Path) -> None:
    """The copy of :func:`copy_database` from the database at the URI ``source``."""
    out = sqlite3.connect(target, timeout=_LOCK_TIMEOUT_S, isolation_level=None)
    try:
        out.execute("PRAGMA main.journal_mode = OFF")  # the caller removes a partial copy
        out.execute("PRAGMA main.synchronous = OFF")  # and flushes a copy it keeps
        if without_blobs:
            _copy_tables(out, source, without_blobs, path)
            return
        reader = sqlite3.connect(source, uri=True, timeout=_LOCK_TIMEOUT_S, isolation_level=None)
        try:
            check_tables(reader, path)
            reader.backup(out)
        finally:
            reader.close()
    finally:
        out.close()


def _copy_tables(
    out: sqlite3.Connection, source: str, without_blobs: frozenset[str], path: Path
) -> None:
    """Create the source's tables and indexes in ``out`` and fill them, in one transaction.

    Every name is quoted (a user's table may be called ``we"ird``); virtual tables (FTS5,
    R*Tree) and their shadow tables are left out: COLMAP has none, and creating a shadow
    table before its virtual table fails. ``out`` takes the source's text encoding (an
    attached database must have the main one's)."""
    _same_encoding(out, source)
    out.execute("ATTACH DATABASE ? AS source", (source,))
    check_tables(out, path, "source")
    plain = {
        name
        for _, name, kind, *_ in out.execute("PRAGMA source.table_list")
        if kind == "table" and not name.startswith("sqlite_")
    }
    out.execute("BEGIN")
    schema = out.execute(
        "SELECT type, name, tbl_name, sql FROM source.sqlite_master WHERE sql IS NOT NULL "
        "AND name NOT LIKE 'sqlite_%' AND type IN ('table', 'index') ORDER BY type = 'index'"
    ).fetchall()
    for kind, name, table, sql in schema:
        if table not in plain:
            continue
        out.execute(sql)
        if kind == "table":
            columns = _columns(out, name, without_blobs)
            quoted = quote_name(name)
            out.execute(f"INSERT INTO main.{quoted} SELECT {columns} FROM source.{quoted}")
    out.execute("COMMIT")
    out.execute("DETACH DATABASE source")


def quote_name(name: str) -> str:
    """``name`` as an SQL identifier, whatever characters it holds."""
    return '"' + name.replace('"', '""') + '"'


def _same_encoding(out: sqlite3.Connection, source: str) -> None:
    """Give the new, empty database ``out`` the text encoding of the database at ``source``."""
    reader = sqlite3.connect(source, uri=True, timeout=_LOCK_TIMEOUT_S, isolation_level=None)
    try:
        (encoding,) = reader.execute("PRAGMA encoding").fetchone()
    finally:
        reader.close()
    if encoding in ("UTF-8", "UTF-16le", "UTF-16be"):
        out.execute(f"PRAGMA main.encoding = '{encoding}'")


def _columns(con: sqlite3.Connection, table: str, without_blobs: frozenset[str]) -> str:
    """The SELECT list that copies ``table``: every column, BLOBs empty for ``without_blobs``."""
    if table not in without_blobs:
        return "*"
    names = [
        "zeroblob(0)" if kind.upper() == "BLOB" else quote_name(name)
        for _, name, kind, *_ in con.execute(f"PRAGMA source.table_info({quote_name(table)})")
    ]
    return ", ".join(names)
