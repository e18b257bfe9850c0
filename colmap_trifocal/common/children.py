"""Child processes for work that may end its process: started, waited for, and ended.

COLMAP aborts the whole process on some failures (an exception thrown in a worker thread:
a full disk during feature extraction), which no Python code can catch. Such work runs in
a child process: the child calls :func:`die_with_parent` first (Linux's
``PR_SET_PDEATHSIG``; not as ``preexec_fn``, which is unsafe in a process with threads),
and :func:`child_process` ends it (SIGTERM, then SIGKILL) whenever the block is left
early, by an error or by Ctrl-C/SIGTERM/SIGHUP here, so the command's own handling of
those signals stays in charge.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Iterator, Sequence
from typing import Any

#: Seconds a child asked to end (SIGTERM) has before it is killed.
END_GRACE_S = 3.0


def die_with_parent(parent: int) -> None:
    """In the child, first: SIGKILL when the parent (process id ``parent``) ends; exit now
    if it already has."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def end_child(child: subprocess.Popen) -> None:
    """End ``child`` if it still runs: SIGTERM, then SIGKILL after :data:`END_GRACE_S`."""
    if child.poll() is None:
        child.terminate()
        try:
            child.wait(timeout=END_GRACE_S)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


@contextlib.contextmanager
def child_process(args: Sequence[str], **popen: Any) -> Iterator[subprocess.Popen]:
    """``subprocess.Popen(args, **popen)``, ended when the block is left (however it is
    left) and its pipes closed."""
    child = subprocess.Popen(list(args), **popen)
    try:
        yield child
    finally:
        end_child(child)
        for stream in (child.stdin, child.stdout, child.stderr):
            if stream is not None:
                stream.close()
