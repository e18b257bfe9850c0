"""The bad-input table's row type, the check every row gets, and the helpers rows share."""

from __future__ import annotations

import hashlib
import os
import resource
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import CliResult, assert_one_error_line, require_rendering, run_cli

PARAMS = [1100.0, 1250.0, 530.0, 370.0]
PRIOR = "1140,1210,545,360"
PRIOR_VALUES = [1140.0, 1210.0, 545.0, 360.0]
#: Enough for the write path to run (fewer triplets, no focal search: faster).
QUICK = ("--prior", PRIOR, "--max-triplets", "3", "--no-focal-search", "--write")
#: The same without ``--write``: a quick calibration that only reads.
QUICK_READ = ("--prior", PRIOR, "--max-triplets", "3", "--no-focal-search")
WIDTH, HEIGHT = 1024, 768
Config = pycolmap.TwoViewGeometryConfiguration


# --------------------------------------------------------------------------- files


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tree(folder: Path) -> dict[str, str]:
    """Every entry below ``folder``: a file's sha256, a symlink's target, what else it is
    (a FIFO or a socket is never opened; a huge sparse file is named by its size)."""
    entries = {}
    for p in sorted(folder.rglob("*")):
        name = str(p.relative_to(folder))
        if p.is_symlink():
            entries[name] = f"-> {os.readlink(p)}"
        elif p.is_file() and p.stat().st_size > 1 << 26:
            entries[name] = f"{p.stat().st_size} bytes"
        elif p.is_file():
            entries[name] = sha256(p)
        elif not p.is_dir():
            entries[name] = "special"
    return entries


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def camera_params(path: Path) -> np.ndarray:
    """The stored params of camera 1 (read without creating companion files)."""
    con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
    try:
        (blob,) = con.execute("SELECT params FROM cameras WHERE camera_id = 1").fetchone()
    finally:
        con.close()
    return np.frombuffer(blob, "<f8").copy()


# --------------------------------------------------------------------------- other processes

_LOCK_HOLDER = """
import sqlite3, sys
con = sqlite3.connect(sys.argv[1], isolation_level=None)
if sys.argv[3]:
    con.execute("PRAGMA journal_mode=" + sys.argv[3])
con.execute(sys.argv[2])
print("locked", flush=True)
sys.stdin.readline()
con.execute("ROLLBACK")
con.close()
"""


@contextmanager
def holding_lock(path: Path, statement: str, journal_mode: str | None = None) -> Iterator[None]:
    """Another process holding ``statement``'s lock (BEGIN IMMEDIATE / EXCLUSIVE) until the
    block ends (then it rolls back and exits)."""
    holder = subprocess.Popen(
        [sys.executable, "-c", _LOCK_HOLDER, str(path), statement, journal_mode or ""],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        yield
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        assert holder.wait(timeout=60) == 0


def limit_file_size(limit: int = 65536) -> Callable[[], None]:
    """In the child: files may not grow beyond ``limit`` bytes (writes fail with EFBIG,
    like a full disk)."""

    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


# --------------------------------------------------------------------------- the rows


@dataclass
class Case:
    """One bad input: how to build it, what to run, what must come out."""

    make: Callable[[Path, Path], Path]  # (folder, good database) -> the database path
    fragment: str
    args: tuple[str, ...] = ()
    status: int = 2
    #: Run while another connection holds a lock: (SQL statement, journal mode or None).
    lock: tuple[str, str | None] | None = None
    #: Run in a child process after this (in the child, before the command line).
    preexec_fn: Callable[[], None] | None = field(default=None, repr=False)
    #: Make the database read-only (chmod 444) before running.
    read_only: bool = False
    #: The command line after the program's name, from (folder, made path, workspace);
    #: default ``calibrate PATH *args``. A workspace given to ``run`` must stay absent.
    argv: Callable[[Path, Path, Path], tuple] | None = field(default=None, repr=False)
    #: A file below the row's folder made unreadable (chmod 000) while the command runs.
    unreadable: str | None = None
    #: Run in a child process with these environment variables (None: removed).
    env: dict[str, str | None] | None = None
    #: The input is used without its bad part: exit 0 and one ``warning:`` line.
    warning: bool = False
    #: The command renders with Open3D offscreen (skipped where it cannot).
    rendering: bool = False
    #: Seconds an output pipe or FIFO waits for its reader (in this process).
    stream_timeout: float | None = None


def command_line(case: Case, folder: Path, path: Path, workspace: Path) -> tuple:
    """The row's arguments; ``{path}`` and ``{folder}`` in them stand for the made path
    and folder."""
    if case.argv is None:
        return ("calibrate", path, *case.args)
    return tuple(
        str(a).format(path=path, folder=folder) if "{" in str(a) else a
        for a in case.argv(folder, path, workspace)
    )


def run_case(
    case: Case,
    args: tuple,
    path: Path,
    run_main: Callable[..., CliResult],
    monkeypatch: pytest.MonkeyPatch,
) -> CliResult:
    """Run the row's command where it must run: a child (a limit, an environment), under
    another process's lock, or in this process."""
    if case.preexec_fn is not None or case.env is not None:
        return run_cli(*args, preexec_fn=case.preexec_fn, env=case.env)
    if case.stream_timeout is not None:
        from colmap_trifocal.common import streams

        monkeypatch.setattr(streams, "STREAM_TIMEOUT_S", case.stream_timeout)
    if case.lock is not None:
        statement, journal_mode = case.lock
        with holding_lock(path, statement, journal_mode):
            return run_main(*args)
    return run_main(*args)


def check_case(
    case: Case,
    good: Path,
    tmp_path: Path,
    run_main: Callable[..., CliResult],
    monkeypatch: pytest.MonkeyPatch,
) -> CliResult:
    """Build the row's input in ``tmp_path/data``, run it, and check everything a bad
    input must give (the module docstring of :mod:`bad_input`)."""
    if case.rendering:
        require_rendering()
    folder = tmp_path / "data"
    folder.mkdir()
    path = case.make(folder, good)
    if case.read_only:
        path.chmod(0o444)
    before = tree(folder)
    workspace = tmp_path / "ws"
    args = command_line(case, folder, path, workspace)
    if case.unreadable is not None:
        (folder / case.unreadable).chmod(0)
    try:
        result = run_case(case, args, path, run_main, monkeypatch)
    finally:
        if case.unreadable is not None:
            (folder / case.unreadable).chmod(0o644)
    if case.warning:
        assert_one_warning_line(result, case.fragment)
    else:
        assert_one_error_line(result, case.fragment, case.status)
    assert tree(folder) == before  # every file byte-identical, none added or removed
    assert not workspace.exists()  # refused before the workspace was made
    # A results table only if computed: outputs (--json, then --write) come last, so a
    # failing one does not lose the estimate.
    assert result.stdout == "" or "--json" in args or "--write" in args or case.warning
    return result


def assert_one_warning_line(result: CliResult, fragment: str) -> None:
    """Exit 0, stderr exactly one line ``warning: ...`` containing ``fragment``."""
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("warning: ") and fragment in lines[0], lines[0]
    assert result.returncode == 0, result.stderr


def main_lines(run_main: Callable[..., CliResult], *args: object) -> tuple[int, list[str]]:
    """Exit status and stderr lines of the command line, in this process."""
    result = run_main(*args)
    return result.returncode, result.stderr.splitlines()


def run_after(function: Callable, action: Callable[[], None]) -> Callable:
    """``function`` followed by ``action`` (fault injection right after a step)."""

    def wrapped(*args: object, **kwargs: object) -> object:
        result = function(*args, **kwargs)
        action()
        return result

    return wrapped


def run_before(function: Callable, action: Callable[[], None]) -> Callable:
    def wrapped(*args: object, **kwargs: object) -> object:
        action()
        return function(*args, **kwargs)

    return wrapped


def table_test(
    cases: dict[str, Case], check: Callable[[Case, CliResult, Path], None] | None = None
) -> Callable[..., None]:
    """The test of a file's table: every row of ``cases`` through :func:`check_case`, then
    ``check(row, result, tmp_path)`` where given (what a file's rows must also give)."""

    @pytest.mark.parametrize("name", list(cases))
    def test_bad_input(
        name: str,
        good_database: Path,
        tmp_path: Path,
        run_main: Callable[..., CliResult],
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        result = check_case(cases[name], good_database, tmp_path, run_main, monkeypatch)
        if check is not None:
            check(cases[name], result, tmp_path)

    return test_bad_input
