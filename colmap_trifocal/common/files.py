"""Writing output files without ever leaving a truncated one behind."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

from .errors import CalibrationError


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


def refuse_overwriting_input(
    output: Path | str, inputs: Iterable[Path | str], option: str, what: str = "an input"
) -> None:
    """Refuse an output path that is one of the command's input files.

    Compares file identities (device and inode), so a symlink or a hard link to an input
    is caught as well as the input's own path. Call it before any work is done.

    Raises:
        CalibrationError: ``output`` exists and is the same file as one of ``inputs``.
    """
    target = file_identity(output)
    if target is None:
        return
    for path in inputs:
        if file_identity(path) == target:
            same = "" if os.fspath(path) == os.fspath(output) else f" (the same file as {path})"
            raise CalibrationError(f"{option} {output} is {what}{same}: refusing to overwrite it")


def write_text_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` without ever leaving a truncated file behind.

    A regular (or new) file is written to a temporary file in the same folder, flushed
    to disk and renamed over ``path``; on any error the temporary file is removed and
    ``path`` is as before. Anything else (``/dev/stdout``, a pipe) is written directly.

    Raises:
        OSError: the file could not be written (no space, no permission, ...).
    """
    path = Path(os.path.realpath(path))  # through a symlink, not over it
    if path.exists() and not path.is_file():
        with path.open("w") as stream:
            stream.write(text)
        return
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "w") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
