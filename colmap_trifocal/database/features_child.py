"""Feature extraction and matching in a child process: COLMAP's aborts become one error.

COLMAP's extraction and matching end the whole process on some failures: a disk that
fills during extraction throws in a reader thread (``std::terminate``, SIGABRT and a glog
stack on stderr), which no Python code can catch. ``run`` (:func:`..run_pipeline`)
therefore builds its database in a child process (:func:`build_database_in_child`); a
child that fails is one :class:`CalibrationError` here, and a Python session or notebook
survives it.

Streams of the child: its progress bars go to its stdout, which is this process's stderr
(so tqdm sees the terminal); its stderr, COLMAP's log, is kept in a temporary file to
explain a failure, or passed through when pycolmap's log level lets everything out.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pycolmap

from ..common.children import child_process
from ..common.errors import CalibrationError

#: The child: ``build_database(**json)`` with tqdm's bars on stdout; a refused input is
#: its message in the file ``sys.argv[2]`` and status 2.
_CHILD = """\
import json, pathlib, sys
from colmap_trifocal.common.children import die_with_parent
die_with_parent(int(sys.argv[3]))
arguments = json.loads(sys.argv[1])
import pycolmap
from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database.features import build_database
pycolmap.logging.minloglevel = arguments.pop("minloglevel")
sys.stderr = sys.stdout  # tqdm writes its bars to sys.stderr
try:
    build_database(**arguments)
except CalibrationError as exc:
    pathlib.Path(sys.argv[2]).write_text(str(exc), encoding="utf-8")
    sys.exit(2)
"""

#: What SQLite and the system say when a disk (or a file size limit) is full.
_NO_SPACE = ("disk is full", "No space left", "File too large", "disk I/O error")
#: pycolmap's error where SQLite could not open or write the database.
_NOT_WRITTEN = "No registered database factory succeeded"
#: Free bytes below which a failed build is put down to a full disk.
_LOW_SPACE = 1 << 20
#: Bytes of the child's log kept to explain a failure (its end).
_LOG_TAIL = 1 << 16


def build_database_in_child(
    image_dir: Path, database: Path, image_names: list[str], **options: Any
) -> Path:
    """:func:`.features.build_database` (``options``: its keyword arguments, JSON values)
    in a child process.

    Ctrl-C or SIGTERM here ends the child first (:func:`..common.children.child_process`),
    and the child dies with this process.

    Raises:
        CalibrationError: the child refused the input (its own one-line message) or failed
            (a full disk, a database pycolmap could not write, or the log's last line).
    """
    arguments = {
        "image_dir": str(image_dir),
        "database": str(database),
        "image_names": image_names,
        "minloglevel": int(pycolmap.logging.minloglevel),
        **options,
    }
    verbose = int(pycolmap.logging.minloglevel) == 0
    with tempfile.TemporaryDirectory(prefix="colmap-trifocal-features-") as tmp:
        refused, log_path = Path(tmp) / "refused.txt", Path(tmp) / "log.txt"
        command = [
            sys.executable,
            "-c",
            _CHILD,
            json.dumps(arguments),
            str(refused),
            str(os.getpid()),
        ]
        with (
            log_path.open("wb") as log,
            child_process(
                command, stdout=_progress_stream(options), stderr=None if verbose else log
            ) as child,
        ):
            status = child.wait()
        if status == 0:
            return Path(database)
        if status == 2 and refused.is_file():
            raise CalibrationError(refused.read_text(encoding="utf-8"))
        with log_path.open("rb") as tail:
            tail.seek(max(log_path.stat().st_size - _LOG_TAIL, 0))
            lines = tail.read().decode("utf-8", "replace").strip().splitlines()
    raise CalibrationError(_child_failure(Path(database), status, lines))


def _progress_stream(options: dict[str, Any]) -> int:
    """The child's stdout: this process's stderr when ``options`` ask for progress bars
    and it is a file descriptor (a notebook's is not: no bars), else nothing."""
    if options.get("progress"):
        try:
            sys.stderr.flush()
            return sys.stderr.fileno()
        except (AttributeError, OSError, ValueError):
            pass
    return subprocess.DEVNULL


def _child_failure(database: Path, status: int, lines: list[str]) -> str:
    """The one-line reason a child with exit ``status`` and log ``lines`` failed."""
    how = f"killed by signal {-status}" if status < 0 else f"exit status {status}"
    reason = _failure_reason(database, lines)
    return f"cannot build the database {database}: {reason} (feature extraction stopped, {how})"


def _failure_reason(database: Path, lines: list[str]) -> str:
    """Why a child writing the COLMAP database ``database`` failed, from its log
    ``lines``: a full disk (what SQLite or the system says, or under :data:`_LOW_SPACE`
    bytes free), a database pycolmap could not write, or the log's last line."""
    text = "\n".join(lines)
    try:
        free: int | None = shutil.disk_usage(database.parent).free
    except OSError:
        free = None
    if any(sign in text for sign in _NO_SPACE) or (free is not None and free < _LOW_SPACE):
        return "no space left on its device"
    if _NOT_WRITTEN in text:
        return "pycolmap could not write it (a full disk, or a file size limit?)"
    return next((line for line in reversed(lines) if line and not line.startswith(" ")), "?")
