"""Fixtures of the bad-input table: the good database every row starts from, a private
copy of it, and the signal dispositions of a terminal."""

from __future__ import annotations

import shutil
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import synthesize

from bad_input.table import PARAMS


@pytest.fixture(scope="session")
def good_database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 images of one PINHOLE camera, exact keypoints, exhaustive verified matches.
    Shared by every row: read it, never write it (``database_copy``)."""
    path = tmp_path_factory.mktemp("good") / "database.db"
    synthesize(path, "PINHOLE", PARAMS)
    return path


@pytest.fixture
def database_copy(good_database: Path, tmp_path: Path) -> Path:
    path = tmp_path / "database.db"
    shutil.copyfile(good_database, path)
    return path


#: Each terminating signal's disposition in an interactive terminal.
SIGNAL_DISPOSITIONS = {
    signal.SIGINT: signal.default_int_handler,
    signal.SIGTERM: signal.SIG_DFL,
    signal.SIGHUP: signal.SIG_DFL,
}


@pytest.fixture(autouse=True)
def usual_signal_dispositions() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP handled as in a terminal, for this process and its children.

    A shell starts a background job with SIGINT ignored, and ``nohup`` ignores SIGHUP;
    the CLI rightly leaves an ignored signal ignored, so the signal tests set the
    dispositions they test instead of inheriting the runner's (children inherit them).
    """
    saved = {signum: signal.getsignal(signum) for signum in SIGNAL_DISPOSITIONS}
    for signum, disposition in SIGNAL_DISPOSITIONS.items():
        signal.signal(signum, disposition)
    yield
    for signum, disposition in saved.items():
        signal.signal(signum, disposition)
