"""What every command shares: one-line messages, the standard streams, output path checks.

The commands check their output paths with these helpers before any work starts, so a
path that cannot be written ends the run at once, with one ``error:`` line and nothing
else on stderr.
"""

from __future__ import annotations

import codecs
import contextlib
import ctypes
import io
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.files import can_create_in, file_identity, write_text_atomically
from ..common.streams import descriptor_of, file_kind, is_stream

#: Exit status of a refused input (after one ``error:`` line on stderr).
EXIT_INPUT_ERROR = 2
#: Names of the standard streams (``stdin``, ``stdout``, ``stderr``) that were closed when
#: the command started (see :func:`standard_streams`).
_CLOSED: set[str] = set()


def one_line(text: str) -> str:
    """``text`` with control characters escaped (a newline in a path becomes ``\\n``)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def say_error(line: str) -> None:
    """Print ``line`` (one ``error: ...`` line) on stderr; a stderr that cannot take it
    (``2>/dev/full``, a closed pipe) loses the line, not the exit status: the command's
    status is what the caller learns then."""
    try:
        print(one_line(line), file=sys.stderr, flush=True)
    except (OSError, ValueError):
        _drop_pending(sys.stderr)


def _drop_pending(stream: object) -> None:
    """Forget what ``stream`` could not write, so that flushing it at exit does not fail
    again (and turn the status into 120): its buffer is replaced by ``/dev/null``'s."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, stream.fileno())  # type: ignore[attr-defined]
        os.close(fd)
        stream.flush()  # type: ignore[attr-defined]
    except (OSError, ValueError, AttributeError):
        pass


def warn(message: str) -> None:
    """A ``warning: ...`` line on stderr (a result the user should look at); control
    characters escaped, so that it stays one line."""
    print(one_line(f"warning: {message}"), file=sys.stderr)


#: What a standard stream whose encoding lacks a character writes instead (``LC_ALL=C
#: PYTHONUTF8=0``, ``PYTHONIOENCODING=ascii``); any other character is escaped (``\\xe9``).
_PLAIN = {
    "\u00b1": "+/-",
    "\u00b7": "*",
    "\u00d7": "x",
    "\u00b0": " deg",
    "\u2013": "-",
    "\u2014": "-",
    "\u2026": "...",
    "\u2192": "->",
    "\u2212": "-",
}
_PLAIN_ERRORS = "colmap_trifocal_plain"


def _plain_replacement(exc: UnicodeError) -> tuple[str | bytes, int]:
    """Codec error handler: a character the encoding lacks, spelled plainly; a byte of an
    undecodable file name (a lone surrogate) written back as that byte (surrogateescape)."""
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    char = exc.object[exc.start]
    if "\udc80" <= char <= "\udcff":
        return bytes([ord(char) - 0xDC00]), exc.start + 1
    return _PLAIN.get(char, char.encode("ascii", "backslashreplace").decode()), exc.start + 1


codecs.register_error(_PLAIN_ERRORS, _plain_replacement)


def encodable_streams() -> None:
    """Standard output and error that can print every table and message whatever the
    locale: where their encoding cannot encode ``±`` (an ASCII locale), a character they
    lack is spelled plainly (``+/-``) instead of raising UnicodeEncodeError mid-table
    (which ended the command before ``--write`` wrote anything)."""
    for stream in (sys.stdout, sys.stderr):
        if not isinstance(stream, io.TextIOWrapper):  # captured, or a replaced stream
            continue
        try:
            "\u00b1\u00b7".encode(stream.encoding)
        except UnicodeEncodeError:
            stream.reconfigure(errors=_PLAIN_ERRORS)
        except LookupError:
            continue


@contextlib.contextmanager
def standard_streams() -> Iterator[None]:
    """Closed standard streams (``>&-``, ``2>&-``) opened on ``/dev/null`` for the block.

    Python leaves ``sys.stdout`` (``sys.stderr``) None when file descriptor 1 (2) is
    closed at start-up. For the block, the descriptor is opened on ``/dev/null``, so no
    file the command opens takes it (C++ libraries write their log lines there), and the
    stream becomes a ``/dev/null`` stream: the command does its job and what it would
    print is dropped. :func:`stdout_closed` tells whether standard output was closed.
    """
    reopened = []
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            devnull = os.open(os.devnull, os.O_RDWR)  # the lowest free descriptor
            if devnull != fd:
                os.dup2(devnull, fd)
                os.close(devnull)
            reopened.append(fd)
    replaced = {}
    for name, mode in (("stdin", "r"), ("stdout", "w"), ("stderr", "w")):
        if getattr(sys, name) is None:
            replaced[name] = open(os.devnull, mode)  # closed when the block ends
            setattr(sys, name, replaced[name])
    _CLOSED.update(replaced)
    encodable_streams()
    try:
        yield
    finally:
        for name, stream in replaced.items():
            setattr(sys, name, None)
            stream.close()
        _CLOSED.difference_update(replaced)
        for fd in reopened:
            os.close(fd)


def stdout_closed() -> bool:
    """Standard output was closed when the command started (``>&-``)."""
    return "stdout" in _CLOSED


def is_stdout(path: Path) -> bool:
    """``-``, or a path naming this process's standard output (``/dev/stdout``, ...)."""
    if str(path) == "-":
        return True
    if stdout_closed():  # descriptor 1 is /dev/null now: only its names count
        return os.path.normpath(path) in ("/dev/stdout", "/dev/fd/1", "/proc/self/fd/1")
    try:
        st = os.fstat(sys.stdout.fileno())
    except (OSError, ValueError):  # no usable file descriptor (captured)
        return False
    return file_identity(path) == (st.st_dev, st.st_ino)


def check_output_file(path: Path, option: str) -> None:
    """Refuse a file output that cannot be written, before any work is done.

    A regular file is written next to itself and renamed (the folder must be writable);
    a device or a pipe is written directly; standard output must be open.
    """
    if is_stdout(path) and stdout_closed():
        raise CalibrationError(f"cannot write {option} {path}: standard output is closed")
    if descriptor_of(path) is not None:  # /dev/stderr, /dev/fd/63: written through it
        return
    if path.exists() and not path.is_file():  # a device or a pipe, written directly
        kind = file_kind(path.stat().st_mode)
        if not is_stream(path) or not os.access(path, os.W_OK):
            raise CalibrationError(f"cannot write {option}: {path} is not a writable file ({kind})")
        return
    folder = Path(os.path.realpath(path)).parent
    if not folder.is_dir():
        raise CalibrationError(f"cannot write {option}: folder {folder} does not exist")
    if not can_create_in(folder):  # the new file is made next to it, then renamed
        raise CalibrationError(f"cannot write {option}: folder {folder} is not writable")


def check_output_folder(path: Path, option: str) -> None:
    """Refuse a folder output that is a file, or that cannot be made (its first existing
    parent is not a writable folder), before any work is done."""
    if path.exists() and not path.is_dir():
        raise CalibrationError(f"cannot write {option}: {path} is not a folder")
    existing = Path(os.path.realpath(path))
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise CalibrationError(f"cannot write {option}: {existing} is not a folder")
    if not can_create_in(existing):
        raise CalibrationError(f"cannot write {option}: folder {existing} is not writable")


def write_text_output(path: Path, text: str, *, to_stdout: bool) -> None:
    """``text`` to standard output or atomically to ``path`` (CalibrationError if not)."""
    try:
        if to_stdout:
            sys.stdout.write(text)
            sys.stdout.flush()
        else:
            write_text_atomically(path, text)
    except OSError as exc:
        raise CalibrationError(f"cannot write {path}: {exc.strerror or exc}") from None


@contextlib.contextmanager
def native_output_silenced(verbosity: int) -> Iterator[None]:
    """File descriptors 1 and 2 on ``/dev/null`` for the block, unless ``-vv``.

    For calls into C++ libraries that print to the process's descriptors themselves
    (Open3D's renderer: Filament's start-up lines, its warnings), which no log level of
    theirs turns off. Python's own streams are flushed first and C's stdio buffers
    before the descriptors are put back.
    """
    if verbosity > 1:
        yield
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        with contextlib.suppress(OSError, AttributeError, TypeError):
            ctypes.CDLL(None).fflush(None)
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)
