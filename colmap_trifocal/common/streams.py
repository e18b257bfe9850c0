"""Files that are not regular files: what may block, opened and written so that nothing does.

An output can be a pipe (``--json >(gzip > f)``, ``/dev/fd/63``), a FIFO made with
``mkfifo``, or a character device (``/dev/null``, ``/dev/full``, a terminal). Opening a FIFO
for writing blocks until a reader opens it, and writing blocks while its reader does not
read; a FIFO read as an input blocks until a writer comes. Here an output stream is opened
with ``O_NONBLOCK`` (a FIFO without a reader is retried until :data:`STREAM_TIMEOUT_S` has
passed) and written in a loop that waits at most :data:`STREAM_TIMEOUT_S` for the reader
each time it stops reading. Inputs are only read when they are regular files, checked
again on the open descriptor (:func:`read_regular_file`), and never read past a size limit.
A signal (Ctrl-C, SIGTERM) ends every wait at once.
"""

from __future__ import annotations

import errno
import os
import select
import stat
import time
from pathlib import Path

#: Seconds an output stream waits for a reader to open it, or to read on once it stopped.
STREAM_TIMEOUT_S = 30.0
#: Seconds between two tries to open a FIFO that has no reader yet.
_RETRY_S = 0.05


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words (``a FIFO``, ``a socket``, ...)."""
    kinds = (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    )
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def is_stream(path: Path | str) -> bool:
    """``path`` names an existing pipe, FIFO or character device (symlinks and
    ``/dev/fd/N`` followed): an output written directly, not replaced by a new file."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISCHR(mode)


class StreamOutput:
    """A pipe, FIFO or character device opened for writing without ever blocking for good.

    Raises OSError from :meth:`open` (no reader within :data:`STREAM_TIMEOUT_S`: ENXIO) and
    from :meth:`write` (the reader went away: EPIPE; it stopped reading: ETIMEDOUT; a full
    device: ENOSPC).
    """

    def __init__(self, path: Path | str, timeout: float | None = None):
        self.path = Path(path)
        self.timeout = STREAM_TIMEOUT_S if timeout is None else timeout
        self.fd: int | None = None

    def open(self) -> StreamOutput:
        """Open the stream; a FIFO without a reader is retried until the timeout."""
        flags = os.O_WRONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                self.fd = os.open(self.path, flags)
                return self
            except OSError as exc:
                if exc.errno != errno.ENXIO:
                    raise
                if time.monotonic() >= deadline:
                    raise OSError(
                        errno.ENXIO,
                        f"no process opened the FIFO for reading within {self.timeout:g} s",
                        str(self.path),
                    ) from None
            time.sleep(_RETRY_S)

    def write(self, data: bytes) -> None:
        """Write all of ``data``, waiting at most the timeout each time the reader stalls."""
        assert self.fd is not None, "open() first"
        view = memoryview(data)
        while view:
            try:
                written = os.write(self.fd, view)
            except BlockingIOError:
                written = 0
            if written:
                view = view[written:]
                continue
            poller = select.poll()
            poller.register(self.fd, select.POLLOUT)
            if not poller.poll(int(self.timeout * 1000)):
                raise OSError(
                    errno.ETIMEDOUT,
                    f"the reader did not read for {self.timeout:g} s",
                    str(self.path),
                )

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> StreamOutput:
        return self.open()

    def __exit__(self, *_: object) -> None:
        self.close()


def descriptor_of(path: Path | str) -> int | None:
    """The open descriptor of this process that ``path`` names (``/dev/stdout``,
    ``/dev/stderr``, ``/dev/fd/N``, ``/proc/self/fd/N``), or None."""
    name = os.path.normpath(str(path))
    named = {"/dev/stdin": 0, "/dev/stdout": 1, "/dev/stderr": 2}
    number: int | None = named.get(name)
    for prefix in ("/dev/fd/", "/proc/self/fd/"):
        if name.startswith(prefix) and name[len(prefix) :].isdigit():
            number = int(name[len(prefix) :])
    if number is None:
        return None
    try:
        os.fstat(number)
    except OSError:
        return None
    return number


def write_special(path: Path | str, data: bytes) -> bool:
    """Write ``data`` to ``path`` if it is not a plain file to be replaced: True then.

    A name of one of this process's descriptors that is a regular file (``--json
    /dev/stderr 2>err.txt``) is written through that descriptor, at its offset (replacing
    the file would cut off what is written to it later); a pipe, FIFO or character device
    (``/dev/fd/63`` of ``>(cmd)``, ``mkfifo``) is written by :func:`write_stream`. False
    for anything else (a regular file, a new one): the caller writes it.
    """
    fd = descriptor_of(path)
    if fd is not None and stat.S_ISREG(os.fstat(fd).st_mode):
        copy = os.dup(fd)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(copy, view) :]
        finally:
            os.close(copy)
        return True
    if is_stream(path):
        write_stream(path, data)
        return True
    return False


def write_stream(path: Path | str, data: bytes) -> None:
    """Write ``data`` to the pipe, FIFO or character device at ``path`` (see
    :class:`StreamOutput`)."""
    with StreamOutput(path) as stream:
        stream.write(data)


def read_regular_file(path: Path | str, limit: int) -> bytes:
    """The bytes of the regular file at ``path`` (symlinks followed), at most ``limit``.

    Checked by ``stat`` before it is opened (a FIFO is never opened), and again on the
    descriptor (opened with ``O_NONBLOCK``: the file may have been replaced meanwhile);
    its size is taken from ``fstat``, so a huge (or sparse) file is refused unread.

    Raises:
        OSError: missing or unreadable, not a regular file (EINVAL, the message names
            what it is), or larger than ``limit`` (EFBIG).
    """
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise OSError(errno.EINVAL, f"not a regular file ({file_kind(mode)})", str(path))
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise OSError(errno.EINVAL, f"not a regular file ({file_kind(st.st_mode)})", str(path))
        if st.st_size > limit:
            raise OSError(
                errno.EFBIG, f"{st.st_size} bytes, more than the {limit} expected", str(path)
            )
        chunks = []
        remaining = limit + 1
        while remaining > 0:
            chunk = os.read(fd, min(remaining, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            remaining -= len(chunk)
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"more than the {limit} bytes expected", str(path))
    return data
