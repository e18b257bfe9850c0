"""The package logger (quiet by default: a NullHandler, level set by the CLI)."""

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import pycolmap

logger = logging.getLogger("colmap_trifocal")
logger.addHandler(logging.NullHandler())


@contextmanager
def keep_colmap_quiet() -> Iterator[None]:
    """Keep COLMAP's log level across a call that resets it.

    ``pycolmap.bundle_adjustment`` (pycolmap 4.2) sets glog's ``minloglevel`` to 0
    and prints INFO lines whatever the level is. When COLMAP is quiet, stderr (file
    descriptor 2, where glog writes) is silenced for the call and the level
    restored afterwards.
    """
    level = pycolmap.logging.minloglevel
    if level < 1:
        yield
        return
    try:
        with silenced_stderr():
            yield
    finally:
        pycolmap.logging.minloglevel = level


@contextmanager
def silenced_stderr() -> Iterator[None]:
    """Send file descriptor 2 (where glog, COLMAP's logger, writes) to /dev/null."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
