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

#: The signals that end a run like Ctrl-C: the write in progress is rolled back (or, once
#: COMMIT has started, finished) and one ``error:`` line is printed.
TERMINATING_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class CalibrationError(RuntimeError):
    """An input problem explained in one line (no traceback for the user)."""


class NoEstimate(CalibrationError):
    """The images give no estimate of a camera: too few images, matches, three-view
    tracks or parallax, not a wrong input.

    ``calibrate`` stops on it like any :class:`CalibrationError`; ``run`` and
    ``reconstruct`` map such a camera from its stored values instead, refining its focal
    length (and distortion) while mapping, as COLMAP would have.
    """


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT), SIGTERM and SIGHUP until the block has finished.

    The first signal held back is then delivered again (``signal.raise_signal``) to the
    handler that was installed before the block: the command line's handler raises
    KeyboardInterrupt and remembers which signal it was; Python's default SIGINT handler
    raises KeyboardInterrupt; a default SIGTERM/SIGHUP action ends the process. Signals
    that were ignored (``nohup``) stay ignored.

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

    previous = {
        signum: signal.signal(signum, remember)
        for signum in TERMINATING_SIGNALS
        if signal.getsignal(signum) is not signal.SIG_IGN  # nohup: stays ignored
    }
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if received:
        signal.raise_signal(received[0])
