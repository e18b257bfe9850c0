"""pycolmap work that writes files, in a child process: COLMAP's aborts become one error.

COLMAP ends the whole process on some failures: a disk that fills during feature
extraction throws in a reader thread, and a database whose last write failed throws again
when it closes, from a destructor (``std::terminate``, SIGABRT and a glog stack on
stderr). No Python code can catch either, and the second comes even after the first was
handled. ``run`` therefore builds its database (:func:`..database.features.build_database`)
and ``demo`` its demo database in a child process (:func:`call_in_child`); a child that
fails is one :class:`CalibrationError` here, and a Python session or notebook survives it.

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

from .children import child_process
from .errors import CalibrationError

#: The child: ``module.function(**json)`` with tqdm's bars on stdout; its return value
#: as JSON in the file ``sys.argv[5]``; a refused input is its message in the file
#: ``sys.argv[3]`` and status 2. SIGTERM and SIGHUP end it through ``SystemExit``, so
#: the function's own clean-up runs where Python has control (a pycolmap call in
#: progress delays it; the parent kills the child after ``END_GRACE_S``). A signal this
#: process inherited as ignored (``nohup``: SIGHUP) stays ignored, as in the parent.
_CHILD = """\
import importlib, json, pathlib, signal, sys
from colmap_trifocal.common.children import die_with_parent
die_with_parent(int(sys.argv[4]))
module, function = sys.argv[1].rsplit(".", 1)
arguments = json.loads(sys.argv[2])
_ignored = {s for s in (signal.SIGTERM, signal.SIGHUP) if signal.getsignal(s) is signal.SIG_IGN}
import pycolmap
from colmap_trifocal.common.errors import CalibrationError
def _end(signum, frame):
    raise SystemExit(128 + signum)  # the function's clean-up runs (its temporary files)
for _signum in (signal.SIGTERM, signal.SIGHUP):  # after pycolmap's import: glog's handler
    signal.signal(_signum, signal.SIG_IGN if _signum in _ignored else _end)  # nohup: ignored
pycolmap.logging.minloglevel = arguments.pop("minloglevel")
sys.stderr = sys.stdout  # tqdm writes its bars to sys.stderr
try:
    result = getattr(importlib.import_module(module), function)(**arguments)
except CalibrationError as exc:
    pathlib.Path(sys.argv[3]).write_text(str(exc), encoding="utf-8")
    sys.exit(2)
pathlib.Path(sys.argv[5]).write_text(json.dumps(result, default=str))
"""

#: What SQLite and the system say when a disk (or a file size limit) is full.
_NO_SPACE = ("disk is full", "No space left", "File too large", "disk I/O error")
#: pycolmap's error where SQLite could not open or write the database.
_NOT_WRITTEN = "No registered database factory succeeded"
#: Free bytes below which a failed child is put down to a full disk.
_LOW_SPACE = 1 << 20
#: Bytes of the child's log kept to explain a failure (its end).
_LOG_TAIL = 1 << 16


def call_in_child(
    function: str, arguments: dict[str, Any], *, output: Path, failure: str, progress: bool
) -> Any:
    """``function(**arguments)`` in a child process; its return value through JSON
    (paths as strings, numpy arrays as lists: ``.tolist()`` them in ``function``).

    Args:
        function: dotted name, ``package.module.function``.
        arguments: its keyword arguments, JSON values.
        output: the file the child writes (its folder's free space explains a failure).
        failure: the start of the error message, as in "cannot build the database X".
        progress: the child's tqdm bars on this process's stderr.

    Ctrl-C or SIGTERM here ends the child first (:func:`.children.child_process`), and
    the child dies with this process.

    Raises:
        CalibrationError: the child refused the input (its own one-line message) or failed
            (``failure``: a full disk, a file pycolmap could not write, or the log's last
            line).
    """
    arguments = {**arguments, "minloglevel": int(pycolmap.logging.minloglevel)}
    verbose = int(pycolmap.logging.minloglevel) == 0
    with tempfile.TemporaryDirectory(prefix="colmap-trifocal-child-") as tmp:
        refused, result, log_path = (Path(tmp) / name for name in ("refused", "result", "log"))
        command = [
            sys.executable,
            "-c",
            _CHILD,
            function,
            json.dumps(arguments),
            str(refused),
            str(os.getpid()),
            str(result),
        ]
        stdout = _progress_stream() if progress else subprocess.DEVNULL
        with (
            log_path.open("wb") as log,
            child_process(command, stdout=stdout, stderr=None if verbose else log) as child,
        ):
            status = child.wait()
        if status == 0:
            return json.loads(result.read_text())
        if status == 2 and refused.is_file():
            raise CalibrationError(refused.read_text(encoding="utf-8"))
        with log_path.open("rb") as tail:
            tail.seek(max(log_path.stat().st_size - _LOG_TAIL, 0))
            lines = tail.read().decode("utf-8", "replace").strip().splitlines()
    how = f"killed by signal {-status}" if status < 0 else f"exit status {status}"
    raise CalibrationError(f"{failure}: {failure_reason(output, lines)} (stopped, {how})")


def _progress_stream() -> int:
    """The child's stdout for progress bars: this process's stderr where it is a file
    descriptor (a notebook's is not: no bars)."""
    try:
        sys.stderr.flush()
        return sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        return subprocess.DEVNULL


def failure_reason(output: Path, lines: list[str]) -> str:
    """Why a child writing ``output`` failed, from its log ``lines``: a full disk (what
    SQLite or the system says, or under :data:`_LOW_SPACE` bytes free), a database
    pycolmap could not write, or the log's last line."""
    text = "\n".join(lines)
    try:
        free: int | None = shutil.disk_usage(output.parent).free
    except OSError:
        free = None
    if any(sign in text for sign in _NO_SPACE) or (free is not None and free < _LOW_SPACE):
        return "no space left on its device"
    if _NOT_WRITTEN in text:
        return "pycolmap could not write it (a full disk, or a file size limit?)"
    return next((line for line in reversed(lines) if line and not line.startswith(" ")), "?")
