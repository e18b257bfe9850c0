"""The process's environment: text encodings, displays, closed or full standard streams,
numerical warnings.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, database_rows, run_cli

from bad_input.table import PARAMS, QUICK, QUICK_READ, camera_params, main_lines, run_after


def test_numerical_warnings_go_to_the_log_not_stderr(
    database_copy: Path,
    monkeypatch: pytest.MonkeyPatch,
    run_main: Callable[..., CliResult],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A RuntimeWarning raised during a run (here a real float overflow in numpy, injected
    after the database is read) is logged (-v shows it); stderr stays empty (issue 15,
    item 8: such lines came before the ``error:`` line)."""
    from colmap_trifocal.cli import batch_input as batch_module

    def overflow() -> None:
        with np.errstate(over="warn"):
            np.float64(1e300) * np.float64(1e300)

    monkeypatch.setattr(
        batch_module, "calibrate_groups", run_after(batch_module.calibrate_groups, overflow)
    )
    with caplog.at_level("INFO", logger="colmap_trifocal"):
        status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK_READ)
    assert (status, lines) == (0, [])
    assert any("RuntimeWarning: overflow" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    "env",
    [
        {"LC_ALL": "C", "LANG": None, "PYTHONUTF8": "0", "PYTHONIOENCODING": None},
        {"PYTHONIOENCODING": "ascii"},
    ],
    ids=["LC_ALL=C PYTHONUTF8=0", "PYTHONIOENCODING=ascii"],
)
def test_an_ascii_stdout_prints_the_table_and_writes(
    env: dict[str, str | None], database_copy: Path
) -> None:
    """A standard output that cannot encode "±": the table says "+/-", ``--write`` writes
    (exit 0, stderr empty, a backup of the same rows; before: UnicodeEncodeError on the
    first row, nothing written)."""
    rows = database_rows(database_copy)
    result = run_cli("calibrate", database_copy, *QUICK, env=env)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    assert "+/-" in result.stdout and "wrote 1 camera(s)" in result.stdout
    np.testing.assert_allclose(camera_params(database_copy), PARAMS, rtol=1e-4)
    assert database_rows(database_copy.with_name("database.db.bak")) == rows


def test_a_full_stderr_keeps_the_exit_status(tmp_path: Path) -> None:
    """``calibrate missing.db 2>/dev/full``: the error line cannot be written, the status
    is still 2 (bad input), not 1 or 120 (a failed print or flush at exit)."""
    with open("/dev/full", "w") as full:
        done = subprocess.run(
            [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(tmp_path / "no.db")],
            stdout=subprocess.PIPE,
            stderr=full,
            timeout=120,
        )
    assert (done.returncode, done.stdout) == (2, b"")
