"""The process's environment: text encodings, displays, closed or full standard streams,
numerical warnings.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult

from bad_input.table import QUICK_READ, main_lines, run_after


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
