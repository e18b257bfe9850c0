"""Writing output files without ever leaving a truncated one behind."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


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
