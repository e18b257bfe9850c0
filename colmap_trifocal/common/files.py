"""Output files: written without ever leaving a truncated one, and never over an input."""

from __future__ import annotations

import errno
import os
import re
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import CalibrationError

if TYPE_CHECKING:
    import pycolmap

#: SQLite's companion files of a database ``NAME``: ``NAME-wal``, ``NAME-shm``, ``NAME-journal``.
SQLITE_COMPANIONS = ("-wal", "-shm", "-journal")


def file_identity(path: Path | str) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of the file at ``path`` (symlinks followed), None if none exists.

    Two paths name the same file (a symlink, a hard link, ``..`` detours) exactly when
    their identities are equal.
    """
    try:
        st = os.stat(path)
    except (OSError, ValueError):  # missing, a dangling link, a NUL in the name
        return None
    return st.st_dev, st.st_ino


@dataclass(frozen=True)
class Input:
    """A path a command reads, and the files read through it.

    ``name`` starts a refusal that concerns the path itself (``--model X is inside
    ...``), ``what`` names one of its files in a refusal (``... is a file of --model``).
    """

    name: str
    path: Path
    what: str
    files: tuple[Path, ...]
    #: A database: its backups (``--write``'s ``<name>.bak``, ``.bak1``, ...) are protected
    #: too, existing or not: an output written after a write would replace the only copy
    #: of the original.
    has_backups: bool = False

    @classmethod
    def database(cls, path: Path, name: str = "DATABASE", what: str = "the database") -> Input:
        """A SQLite database with its companion files (``-wal``, ``-shm``, ``-journal``)."""
        companions = [Path(f"{path}{suffix}") for suffix in SQLITE_COMPANIONS]
        return cls(name, path, what, (path, *companions), has_backups=True)

    def is_backup_name(self, real: Path) -> bool:
        """Whether the real path ``real`` is (or would be) a backup of this database."""
        if not self.has_backups:
            return False
        folder = Path(os.path.realpath(self.path.parent))
        pattern = rf"\.?{re.escape(self.path.name)}\.bak(\d*|\.\w{{8}}\.tmp)"
        return real.parent == folder and re.fullmatch(pattern, real.name) is not None

    @classmethod
    def folder(cls, path: Path, name: str, suffixes: Sequence[str] | None = None) -> Input:
        """A folder whose files (directly in it; with one of ``suffixes``, lower case, if
        given) are read: an image folder, a COLMAP model folder."""
        files = (
            tuple(
                p
                for p in sorted(path.iterdir())
                if p.is_file() and (suffixes is None or p.suffix.lower() in suffixes)
            )
            if path.is_dir()
            else ()
        )
        return cls(name, path, f"a file of {name}", files)


@dataclass(frozen=True)
class Output:
    """A path a command writes: a file it replaces, or (``folder``) a folder it fills or
    empties.

    ``option`` starts the refusal (``--json OUT is ...``); ``hint`` ends it.
    """

    option: str
    path: Path
    hint: str = ""
    folder: bool = False


def refuse_outputs_over_inputs(outputs: Iterable[Output], inputs: Iterable[Input]) -> None:
    """The rule that no output overwrites or deletes an input; call it before any work.

    An existing output is refused when it is the same file as one of the inputs' files
    (device and inode: a symlink, a hard link, a ``..`` detour or a relative path to an
    input is caught as well as its own path), and, when it is a folder (replaced or
    emptied), when any input or input file lies inside it (its real path below the
    folder; a symlink into the folder counts). An output that does not exist yet
    replaces nothing: a new file inside an input folder is allowed, but not one named
    as a database input's backup (:meth:`Input.is_backup_name`). The outputs are
    also checked against each other (:func:`_refuse_overlapping_outputs`).

    Raises:
        CalibrationError: an output is an input, or holds one, or is another output.
    """
    outputs = list(outputs)
    inputs = list(inputs)
    _refuse_overlapping_outputs(outputs)
    _refuse_backup_names(outputs, inputs)
    existing = [(output, file_identity(output.path)) for output in outputs]
    files = {identity: output for output, identity in existing if identity is not None}
    folders = {identity: output for identity, output in files.items() if os.path.isdir(output.path)}
    if not files:
        return
    seen: dict[Path, tuple[int, int] | None] = {}  # identities of the folders above inputs
    for given in inputs:
        for path in (given.path, *given.files):
            identity = file_identity(path)
            if identity is None:
                continue
            output = files.get(identity)
            if output is not None and identity not in folders:
                _refuse_same_file(output, given, path)
            if folders:
                _refuse_inside(given, path, folders, seen)


def _refuse_backup_names(outputs: list[Output], inputs: list[Input]) -> None:
    """Refuse an output named as a database input's backup (``--write`` keeps the
    original there)."""
    for written in outputs:
        real = Path(os.path.realpath(written.path))
        for given in inputs:
            if given.is_backup_name(real):
                raise CalibrationError(
                    f"{written.option} {written.path} is a backup name of {given.what} "
                    f"{given.path} (--write keeps the original there): refusing to write "
                    f"it{written.hint}"
                )


def _refuse_same_file(output: Output, given: Input, path: Path) -> None:
    """Refuse ``output``, the same file as ``path`` (``given`` or one of its files)."""
    same = "" if os.fspath(path) == os.fspath(output.path) else f" (the same file as {path})"
    what = given.what
    if path != given.path and not os.path.isdir(given.path):
        what = f"{what}'s companion file"  # SQLite's -wal, -shm, -journal
    raise CalibrationError(
        f"{output.option} {output.path} is {what}{same}: refusing to overwrite it{output.hint}"
    )


def _refuse_inside(
    given: Input,
    path: Path,
    folders: dict[tuple[int, int], Output],
    seen: dict[Path, tuple[int, int] | None],
) -> None:
    """Refuse a folder output that holds ``path`` (``given`` or one of its files);
    ``seen`` caches the identities of the folders above inputs."""
    for folder in _real_ancestors(path):
        if folder not in seen:
            seen[folder] = file_identity(folder)
        output = folders.get(seen[folder])  # type: ignore[arg-type]
        if output is not None:
            raise CalibrationError(
                f"{given.name} {given.path} is inside {output.option} {output.path}: "
                f"refusing to overwrite it{output.hint}"
            )


def _refuse_overlapping_outputs(outputs: Sequence[Output]) -> None:
    """Refuse two outputs at one real path, or one inside a folder output (say a PNG
    named ``WORKSPACE/report.json``: written after the report, it would replace it).
    Compared by real path, since most outputs do not exist yet."""
    real = [Path(os.path.realpath(output.path)) for output in outputs]
    for i, output in enumerate(outputs):
        for j, other in enumerate(outputs):
            if i < j and real[i] == real[j]:
                raise CalibrationError(
                    f"{other.option} {other.path} is also {output.option} {output.path}: "
                    "refusing to write it twice"
                )
            if other.folder and real[j] in real[i].parents:
                raise CalibrationError(
                    f"{output.option} {output.path} is inside {other.option} {other.path}: "
                    f"refusing to overwrite it{other.hint}"
                )


def _real_ancestors(path: Path) -> list[Path]:
    """``path`` with symlinks and ``..`` resolved, then each folder above it."""
    real = Path(os.path.realpath(path))
    return [real, *real.parents]


def can_create_in(folder: Path) -> bool:
    """A file can be created in ``folder``: tried with a hidden temporary file, removed at
    once (permission bits say nothing for root, nor on a read-only file system)."""
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".colmap-trifocal.", suffix=".probe")
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


def missing_folders(path: Path) -> list[Path]:
    """``path`` and its parents that do not exist yet, deepest first: what a
    ``mkdir(parents=True)`` of ``path`` makes, for :func:`remove_if_empty` to undo."""
    missing = []
    while not path.exists() and path != path.parent:
        missing.append(path)
        path = path.parent
    return missing


def remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders a command made (deepest first) while they are empty; stop at
    the first that is not (a partial result, another's file: kept)."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def write_text_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` without ever leaving a truncated file behind.

    A regular (or new) file is written to a temporary file in the same folder, flushed
    to disk and renamed over ``path``; on any error the temporary file is removed and
    ``path`` is as before. Anything else (``/dev/stdout``, a pipe, a FIFO: see
    :func:`.streams.write_special`) is written directly, never blocking for good.

    Raises:
        OSError: the file could not be written (no space, no permission, ...).
    """
    from .streams import write_special

    if write_special(path, text.encode("utf-8")):  # a pipe, a FIFO, /dev/stderr, ...
        return
    path = Path(os.path.realpath(path))  # through a symlink, not over it
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "w", encoding="utf-8") as stream:  # whatever the locale
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException as exc:
        Path(temporary).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None:  # a write or fsync: say where
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from exc
        raise


def write_model_atomically(reconstruction: pycolmap.Reconstruction, folder: Path) -> None:
    """``reconstruction.write`` into ``folder`` (new, or an empty folder) without ever
    leaving part of a model there.

    The files go into a temporary folder beside ``folder``, are read back, and the folder
    is renamed to ``folder`` only when the model read back has every camera, image and
    point: on a full disk pycolmap writes truncated files without raising
    (docs/reliability.md). On any error the temporary folder is removed.

    Raises:
        CalibrationError: the model could not be written (the reason, and the folder).
    """
    import shutil

    folder = Path(os.path.realpath(folder))  # through a symlink, not over it
    folder.parent.mkdir(parents=True, exist_ok=True)
    temporary = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}.", suffix=".tmp"))
    try:
        os.chmod(temporary, 0o777 & ~_umask())  # as mkdir makes a folder (mkdtemp: 0700)
        reconstruction.write(temporary)
        if not _read_back(temporary, _model_counts(reconstruction)):
            raise OSError(errno.ENOSPC, "the files read back are incomplete (a full disk?)")
        os.replace(temporary, folder)
    except (OSError, RuntimeError, ValueError) as exc:
        shutil.rmtree(temporary, ignore_errors=True)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else None
        reason = reason or (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
        raise CalibrationError(f"cannot write the model to {folder}: {reason}") from None
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise


def _read_back(folder: Path, counts: tuple[int, int, int, int]) -> bool:
    """Whether the model in ``folder`` reads back with ``counts`` (:func:`_model_counts`);
    pycolmap raises anything (``IndexError``, ``RuntimeError``) on truncated files."""
    import pycolmap

    try:
        return _model_counts(pycolmap.Reconstruction(folder)) == counts
    except Exception:  # noqa: BLE001 (any failure to read is an incomplete model)
        return False


def _model_counts(reconstruction: pycolmap.Reconstruction) -> tuple[int, int, int, int]:
    """Cameras, images, registered images and points of a model."""
    return (
        reconstruction.num_cameras(),
        reconstruction.num_images(),
        reconstruction.num_reg_images(),
        reconstruction.num_points3D(),
    )


def _umask() -> int:
    """The process's file mode creation mask (read by setting it and setting it back)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


def remove_database_files(path: Path) -> None:
    """Remove the SQLite database ``path`` and its companions (:data:`SQLITE_COMPANIONS`)
    where they exist: a partial database this tool was writing is worth nothing."""
    for leftover in (Path(path), *(Path(f"{path}{suffix}") for suffix in SQLITE_COMPANIONS)):
        leftover.unlink(missing_ok=True)
