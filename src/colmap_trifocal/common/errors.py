"""User-facing errors, and Ctrl-C around steps that must not be split.

Every problem caused by the user's input (a missing file, a database without
matches, a malformed prior, ...) is raised as :class:`CalibrationError`. The
command line prints its message as a single ``error: ...`` line and exits with
status 2; nothing else is caught there, so genuine bugs still show a traceback.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


class CalibrationError(RuntimeError):
    """An input problem explained in one line (no traceback for the user)."""


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT) until the block has finished, then raise KeyboardInterrupt.

    For the few statements that must not be split: creating a file and remembering
    it, so that the clean-up after an interrupt knows what exists; COMMIT and
    remembering that it happened; ``fork()``, whose at-fork hooks would swallow the
    KeyboardInterrupt ("Exception ignored in ..."). Keep such blocks short: Ctrl-C does
    nothing until they end. A no-op outside the main thread, where Python cannot
    install signal handlers.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def remember(signum: int, _frame: object) -> None:
        received.append(signum)

    previous = signal.signal(signal.SIGINT, remember)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt
