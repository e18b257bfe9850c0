"""Other processes and signals: locks held elsewhere, Ctrl-C, SIGTERM and SIGHUP during
``--write`` (fault injection in this process and real signals to a subprocess).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, database_rows, run_cli

from bad_input.builders import (
    copy_good,
    rollback_journal_copy,
)
from bad_input.table import (
    PARAMS,
    PRIOR,
    QUICK,
    Case,
    camera_params,
    listing,
    main_lines,
    run_after,
    run_before,
    sha256,
    table_test,
)
from colmap_trifocal.cli.signals import watching_signals
from colmap_trifocal.database import backup as backup_module
from colmap_trifocal.database import sqlite_files
from colmap_trifocal.database import writing as database_module

CASES: dict[str, Case] = {
    "locked (exclusive, rollback journal)": Case(
        rollback_journal_copy, "locked by another process", lock=("BEGIN EXCLUSIVE", None)
    ),
    "locked (immediate) with --write": Case(
        copy_good,
        "locked by another process",
        args=("--prior", PRIOR, "--write"),
        lock=("BEGIN IMMEDIATE", None),
    ),
}


test_bad_input = table_test(CASES)


def _raise_interrupt() -> None:
    raise KeyboardInterrupt


def _send_sigint() -> None:
    """A real SIGINT to this process (handled at the next bytecode, like Ctrl-C)."""
    os.kill(os.getpid(), signal.SIGINT)


def _send_sigterm() -> None:
    """A real SIGTERM to this process (``kill PID``, a service manager stopping a job)."""
    os.kill(os.getpid(), signal.SIGTERM)


def _send_sighup() -> None:
    """A real SIGHUP to this process (the terminal was closed)."""
    os.kill(os.getpid(), signal.SIGHUP)


#: How each signal ends a run: its one line and exit status.
SIGNAL_ENDINGS = {
    "sigint": (_send_sigint, "error: interrupted", 130),
    "sigterm": (_send_sigterm, "error: terminated", 143),
    "sighup": (_send_sighup, "error: terminated (hangup)", 129),
}


def test_interrupt_between_update_and_commit(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """KeyboardInterrupt right after the UPDATE, before COMMIT: nothing written, no backup."""
    before = sha256(database_copy)
    original = database_module._update_params
    calls: list[int] = []
    monkeypatch.setattr(
        database_module,
        "_update_params",
        run_after(original, lambda: calls.append(1) or _raise_interrupt()),
    )
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert calls == [1]  # the UPDATE did run
    assert status == 130
    assert lines == ["error: interrupted"]
    assert sha256(database_copy) == before
    assert listing(database_copy.parent) == ["database.db"]


@pytest.mark.parametrize(
    ("function", "inject"),
    [
        ("_claim_backup_path", "after-sigint"),  # the empty temporary exists, no copy yet
        ("_copy_database", "before-sigint"),  # Ctrl-C while copying
        ("_copy_database", "after-raise"),  # the complete copy exists, not yet renamed
        ("_publish_backup", "after-sigint"),  # the .bak exists, nothing written yet
        ("_update_params", "before-raise"),
        ("_update_params", "after-sigint"),
        # SIGTERM and SIGHUP are handled like Ctrl-C (issue 15, item 1).
        ("_claim_backup_path", "after-sigterm"),
        ("_copy_database", "before-sigterm"),
        ("_publish_backup", "after-sighup"),
        ("_update_params", "after-sighup"),
    ],
)
def test_interrupt_before_commit_leaves_nothing(
    function: str,
    inject: str,
    database_copy: Path,
    monkeypatch: pytest.MonkeyPatch,
    run_main: Callable[..., CliResult],
) -> None:
    """Interrupted at any step before COMMIT: database byte-identical, no backup left."""
    before = sha256(database_copy)
    when, how = inject.split("-")
    action, line, expected_status = SIGNAL_ENDINGS.get(
        how, (_raise_interrupt, *SIGNAL_ENDINGS["sigint"][1:])
    )
    wrap = run_after if when == "after" else run_before
    module = backup_module if hasattr(backup_module, function) else database_module
    monkeypatch.setattr(module, function, wrap(getattr(module, function), action))
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert (status, lines) == (expected_status, [line])
    assert sha256(database_copy) == before
    assert listing(database_copy.parent) == ["database.db"]


def test_interrupt_during_commit_is_held_until_written(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """A SIGINT arriving as COMMIT starts: the commit completes, the backup is kept, 130."""
    original_bytes = database_copy.read_bytes()
    monkeypatch.setattr(
        database_module, "_commit", run_before(database_module._commit, _send_sigint)
    )
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert status == 130
    assert len(lines) == 1 and lines[0].startswith("error: interrupted (after the new intrinsics")
    assert "backup: " in lines[0]
    backup = database_copy.with_name("database.db.bak")
    assert database_rows(backup) == database_rows(original_bytes)
    np.testing.assert_allclose(camera_params(database_copy), PARAMS, rtol=1e-5)
    assert listing(database_copy.parent) == ["database.db", "database.db.bak"]


@pytest.mark.parametrize("how", ["sigterm", "sighup"])
def test_signal_during_commit_is_held_until_written(
    how: str,
    database_copy: Path,
    monkeypatch: pytest.MonkeyPatch,
    run_main: Callable[..., CliResult],
) -> None:
    """Any of the three signals as COMMIT starts: the commit completes, the backup is kept."""
    send, line, expected_status = SIGNAL_ENDINGS[how]
    monkeypatch.setattr(database_module, "_commit", run_before(database_module._commit, send))
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert status == expected_status
    assert len(lines) == 1 and lines[0].startswith(f"{line} (after the new intrinsics"), lines
    np.testing.assert_allclose(camera_params(database_copy), PARAMS, rtol=1e-5)
    assert listing(database_copy.parent) == ["database.db", "database.db.bak"]


def test_backup_is_copied_under_a_temporary_name(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """While the copy is made no ``.bak`` exists: a process killed meanwhile (even by
    SIGKILL) never leaves a partial ``.bak`` that a later ``--write`` would keep as
    ``.bak``, making ``.bak1`` (issue 15, item 1). The complete copy is renamed."""
    original = database_copy.read_bytes()
    seen: list[list[str]] = []
    copy = backup_module._copy_database

    def watched(path: Path, target: Path) -> None:
        seen.append(listing(path.parent))
        copy(path, target)
        seen.append(listing(path.parent))

    monkeypatch.setattr(backup_module, "_copy_database", watched)
    status, _ = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert status == 0
    assert seen and not any("database.db.bak" in names for names in seen), seen
    assert listing(database_copy.parent) == ["database.db", "database.db.bak"]
    assert database_rows(database_copy.with_name("database.db.bak")) == database_rows(original)


def test_a_second_write_keeps_the_first_backup(
    database_copy: Path, run_main: Callable[..., CliResult]
) -> None:
    """An existing ``.bak`` is never overwritten: the next backup is ``.bak1``."""
    original = database_copy.read_bytes()
    assert run_main("calibrate", database_copy, *QUICK).returncode == 0
    first = database_copy.read_bytes()
    assert run_main("calibrate", database_copy, *QUICK).returncode == 0
    assert listing(database_copy.parent) == ["database.db", "database.db.bak", "database.db.bak1"]
    assert database_rows(database_copy.with_name("database.db.bak")) == database_rows(original)
    assert database_rows(database_copy.with_name("database.db.bak1")) == database_rows(first)


#: In a child: write new params to the database argv[1] with the backup's copy replaced by
#: a partial copy, then argv[2]: "kill" (SIGKILL itself) or "wait" (hold the write lock
#: until stdin closes).
_HALF_A_BACKUP = """
import os, signal, sys
from pathlib import Path
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.database import backup
from colmap_trifocal.database.writing import write_intrinsics

def partial_copy(path, target):
    target.write_bytes(path.read_bytes()[:4096])
    if sys.argv[2] == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    print("copying", flush=True)
    sys.stdin.readline()
    os._exit(0)

backup._copy_database = partial_copy
path = Path(sys.argv[1])
cameras = read_database(path).cameras
write_intrinsics(path, {i: c.with_intrinsics(1000, 1000, 500, 400) for i, c in cameras.items()})
"""


def _temporary_copies(folder: Path) -> list[str]:
    return [name for name in listing(folder) if name.startswith(".database.db.bak.")]


def test_a_backup_killed_while_copying_is_removed_by_the_next_write(
    database_copy: Path, run_main: Callable[..., CliResult]
) -> None:
    """SIGKILL while the backup is copied (nothing can clean up) leaves its hidden temporary
    copy behind; the next ``--write`` removes it, and keeps only its own ``.bak``."""
    original = database_copy.read_bytes()
    child = subprocess.run(
        [sys.executable, "-c", _HALF_A_BACKUP, str(database_copy), "kill"], timeout=120
    )
    assert child.returncode == -signal.SIGKILL
    assert database_copy.read_bytes() == original
    (left,) = _temporary_copies(database_copy.parent)
    assert re.fullmatch(r"\.database\.db\.bak\.\w{8}\.tmp", left)
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert (status, lines) == (0, [])
    assert listing(database_copy.parent) == ["database.db", "database.db.bak"]
    assert database_rows(database_copy.with_name("database.db.bak")) == database_rows(original)


def test_the_copy_of_a_running_write_is_left_alone(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """A write that is still copying its backup holds the write lock: another ``--write``
    is refused as locked and removes nothing."""
    monkeypatch.setattr(sqlite_files, "_LOCK_TIMEOUT_S", 0.05)
    child = subprocess.Popen(
        [sys.executable, "-c", _HALF_A_BACKUP, str(database_copy), "wait"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout is not None and child.stdout.readline() == "copying\n"
        (running,) = _temporary_copies(database_copy.parent)
        status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
        locked = f"error: database is locked by another process: {database_copy}"
        assert (status, lines) == (2, [locked])
        assert _temporary_copies(database_copy.parent) == [running]
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait(timeout=60)


def _write_state(path: Path, original: bytes, new_params: np.ndarray) -> str:
    """'untouched' or 'written'; fails on any other state of the database and its backups."""
    names = listing(path.parent)
    if path.read_bytes() == original:
        assert names == ["database.db"], names
        return "untouched"
    assert names == ["database.db", "database.db.bak"], names
    assert database_rows(path.with_name("database.db.bak")) == database_rows(original)
    np.testing.assert_array_equal(camera_params(path), new_params)
    return "written"


@pytest.mark.slow  # 12 real runs (SIGINT), 5 (SIGTERM, SIGHUP): 30-70 s each
@pytest.mark.parametrize(
    ("signum", "line", "status", "runs"),
    [
        (signal.SIGINT, "error: interrupted", 130, 6),
        # Issue 15, item 1: these ended with glog's stack dump and a partial .bak.
        (signal.SIGTERM, "error: terminated", 143, 3),
        (signal.SIGHUP, "error: terminated (hangup)", 129, 3),
    ],
    ids=["SIGINT", "SIGTERM", "SIGHUP"],
)
def test_signal_at_any_time_during_write(
    signum: int, line: str, status: int, runs: int, good_database: Path, tmp_path: Path
) -> None:
    """Real signals, as a terminal (or ``kill``) sends them to the process group, across
    a whole run.

    Afterwards the database is either byte-identical with no backup, or holds exactly
    the new params with a ``.bak`` equal to the original: never a half state, never a
    partial backup. The delays are spread over the measured duration of an
    uninterrupted run, from 0.4 s (the interpreter itself is up: a SIGINT before
    ``main`` runs is Python's own traceback) to its end; a last run is not interrupted.
    """
    original = good_database.read_bytes()
    reference = tmp_path / "reference" / "database.db"
    reference.parent.mkdir()
    reference.write_bytes(original)
    start = time.perf_counter()
    completed = run_cli("calibrate", reference, "--prior", PRIOR, "--write")
    duration = time.perf_counter() - start
    assert completed.returncode == 0, completed.stderr
    new_params = camera_params(reference)
    np.testing.assert_allclose(new_params, PARAMS, rtol=1e-4)
    delays: list[float | None] = [0.4, *np.linspace(0.6, duration, runs), None]
    states = []
    for index, delay in enumerate(delays):
        path = tmp_path / f"run{index}" / "database.db"
        path.parent.mkdir()
        path.write_bytes(original)
        process = subprocess.Popen(
            [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(path)]
            + ["--prior", PRIOR, "--write"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # its own process group, like a terminal job
        )
        if delay is not None:
            time.sleep(delay)
            try:
                os.killpg(process.pid, signum)
            except ProcessLookupError:  # already finished
                pass
        stdout, stderr = process.communicate(timeout=120)
        state = _write_state(path, original, new_params)
        states.append(state)
        assert "Traceback" not in stderr, (delay, stderr)
        if stderr == "" and "wrote 1 camera(s)" in stdout:
            # Finished; status 0, or -SIGINT when the signal came during the interpreter's
            # shutdown, after it had put back the default handler (seen at ~duration).
            assert process.returncode in (0, -signum) and state == "written", delay
            continue
        if signum != signal.SIGINT and process.returncode == -signum and stderr == "":
            # SIGTERM/SIGHUP before main() installed its handler: the default action,
            # which ends the process before it has opened anything.
            assert state == "untouched", delay
            continue
        # Exit status 130, or killed by SIGINT (a shell shows 130 as well). CPython ends
        # that way, after main() returned 130, when the KeyboardInterrupt was raised
        # inside an exec()/eval() of a string (dataclass and namedtuple definitions of the
        # modules still being imported): it remembers it as "unhandled" and re-raises
        # SIGINT at exit (also after a SIGTERM or SIGHUP, which main() turns into the same
        # interrupt; seen at 0.4 s on a loaded machine).
        assert process.returncode in (status, -signum, -signal.SIGINT), (delay, stderr)
        lines = stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith(line), (delay, stderr)
    assert states[0] == "untouched" and states[-1] == "written", states


def test_an_interrupt_inside_a_weakref_callback_is_raised_again_without_a_traceback(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """Python runs a signal's handler between any two bytecodes, also inside a weakref
    callback, where the handler's KeyboardInterrupt cannot propagate: Python printed it
    with a traceback ("Exception ignored in ...") and the run went on, the interrupt lost
    (CI caught it once, 1.3 s into ``test_signal_at_any_time_during_write[SIGINT]``).
    Under the command line's watch nothing is printed and the interrupt reaches the
    main flow."""

    class Thing:
        pass

    def callback(_reference: object) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10_000):  # the handler runs here, inside the callback
            pass

    deadline = time.monotonic() + 5.0
    with pytest.raises(KeyboardInterrupt), watching_signals() as watch:
        thing = Thing()
        reference = weakref.ref(thing, callback)
        del thing  # the callback runs
        while time.monotonic() < deadline:
            pass
    assert reference() is None
    assert watch.signum == signal.SIGINT
    assert time.monotonic() < deadline
    assert "Traceback" not in capfd.readouterr().err
