"""Signals on the command line: SIGINT, SIGTERM and SIGHUP end a run with one ``error:`` line.

All three end a run the same way: the write in progress is rolled back (or, once COMMIT
has started, finished: :func:`colmap_trifocal.common.errors.interrupts_deferred`) and one
line is printed, ``error: interrupted`` (exit 130), ``error: terminated`` (143) or
``error: terminated (hangup)`` (129). A signal the caller ignores (``nohup``, a
background job's SIGINT) stays ignored.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from ..common.errors import TERMINATING_SIGNALS
from .output import say_error


class InterruptWatch:
    """Handler of SIGINT, SIGTERM and SIGHUP: raises KeyboardInterrupt and remembers the signal.

    Some libraries turn the KeyboardInterrupt into another exception, e.g. pycolmap's C++
    module, interrupted while it loads, fails with an ``ImportError``/``RuntimeError``;
    :func:`colmap_trifocal.cli.main` still reports such a run as interrupted.
    """

    def __init__(self) -> None:
        self.signum: int | None = None

    @property
    def received(self) -> bool:
        """A signal has arrived (whatever exception it turned into)."""
        return self.signum is not None

    def __call__(self, signum: int, frame: object) -> None:
        if self.signum is None:
            self.signum = signum
        raise KeyboardInterrupt

    def again(self, signum: int, frame: object) -> None:
        """SIGALRM's handler: the signal received, delivered once more to whichever
        handler it now has (this watch, or a block that holds signals back:
        :func:`colmap_trifocal.common.errors.interrupts_deferred`)."""
        if self.signum is not None:
            signal.raise_signal(self.signum)

    def unraisable(self, unraisable: Any, previous: Any) -> None:
        """``sys.unraisablehook`` while the watch is installed.

        Python runs a signal's handler between any two bytecodes, also inside a weakref
        callback or a ``__del__``. A KeyboardInterrupt raised there cannot propagate:
        Python prints it with its traceback and goes on, and the interrupt would be
        lost. Instead nothing is printed, and the signal is delivered again a
        millisecond later (SIGALRM, :meth:`again`), to whatever the main thread then
        runs: once this hook has returned. Any other unraisable exception goes to
        ``previous``.
        """
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and self.received:
            alarm = getattr(signal, "SIGALRM", None)  # not on Windows
            if alarm is not None and signal.getsignal(alarm) == self.again:
                signal.setitimer(signal.ITIMER_REAL, REARM_SECONDS)
            return
        previous(unraisable)

    def install(self) -> dict[int, Any]:
        """Install for every signal not ignored (``nohup``); the previous handlers."""
        return {
            signum: signal.signal(signum, self)
            for signum in TERMINATING_SIGNALS
            if signal.getsignal(signum) is not signal.SIG_IGN
        }


#: Delay (s) after which an interrupt that Python could not raise is raised again.
REARM_SECONDS = 0.001


@contextmanager
def watching_signals() -> Iterator[InterruptWatch]:
    """An :class:`InterruptWatch` installed for the block (main thread only), with its
    ``sys.unraisablehook``; then the previous handlers and hook put back."""
    watch = InterruptWatch()
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = watch.install() if in_main_thread else {}
    previous_hook = sys.unraisablehook
    rearms = in_main_thread and hasattr(signal, "setitimer")  # not on Windows
    previous_alarm = signal.signal(signal.SIGALRM, watch.again) if rearms else None
    if in_main_thread:
        sys.unraisablehook = lambda unraisable: watch.unraisable(unraisable, previous_hook)
    try:
        yield watch
    finally:
        if in_main_thread:
            sys.unraisablehook = previous_hook
        if rearms:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous_alarm)
        for signum, handler in previous.items():
            signal.signal(signum, handler)


@contextmanager
def glog_cannot_take_sigterm(watch: InterruptWatch) -> Iterator[None]:
    """Hold SIGTERM back while pycolmap loads; then install ``watch`` for it again.

    Importing pycolmap installs glog's failure handler for SIGTERM (and SIGSEGV, ...),
    which ends the process with a stack dump and no clean-up. A SIGTERM that arrives
    meanwhile stays pending (``pthread_sigmask``) and reaches ``watch`` afterwards.
    """
    in_main_thread = threading.current_thread() is threading.main_thread()
    if not in_main_thread or signal.getsignal(signal.SIGTERM) is not watch:
        yield
        return
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, watch)
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def report_interrupted(exc: BaseException, signum: int | None = None) -> int:
    """Print the one line for an interrupted run; its exit status (128 + the signal).

    Ctrl-C (SIGINT, also ``signum`` None) is "interrupted", SIGTERM and SIGHUP
    "terminated"; the exception's text, if any, follows in parentheses.
    """
    detail = f" ({exc})" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
    signum = signal.SIGINT if signum is None else signum
    word = "interrupted" if signum == signal.SIGINT else "terminated"
    if signum == signal.SIGHUP:
        detail = f" (hangup){detail}"
    say_error(f"error: {word}{detail}")
    return 128 + int(signum)
