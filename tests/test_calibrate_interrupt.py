"""A signal in the middle of ``calibrate``'s parallel tensor stage ends the process promptly.

The tensors of the triplets are estimated by forked worker processes
(``common.parallel.map_jobs``), which leave the signals to the main thread; it waits on
their results. A SIGTERM (or Ctrl-C, or a hangup) must end the
run at once, with the documented one line and exit status, not after the remaining
triplets. The process is the point here (real signals, real worker processes): a subprocess
on a synthetic database whose tensor stage lasts seconds.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import synthesize

#: A generous bound: the jobs running when the signal comes finish (milliseconds each);
#: the stage itself, uninterrupted, lasts seconds.
PROMPT_SECONDS = 10.0
TRIPLETS = 120


@pytest.fixture(scope="module")
def database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """10 images of one PINHOLE camera: 120 triplets, a tensor stage of a few seconds."""
    path = tmp_path_factory.mktemp("interrupt") / "database.db"
    synthesize(path, "PINHOLE", [1100.0, 1250.0, 530.0, 370.0], frames=10, points=300)
    return path


@pytest.mark.parametrize(
    ("signum", "line", "status"),
    [
        (signal.SIGTERM, "error: terminated", 143),
        (signal.SIGINT, "error: interrupted", 130),
        (signal.SIGHUP, "error: terminated (hangup)", 129),
    ],
    ids=["SIGTERM", "SIGINT", "SIGHUP"],
)
def test_signal_during_tensor_stage_ends_promptly(
    signum: int, line: str, status: int, database: Path
) -> None:
    """The signal is sent once the first triplet's tensor is logged (``-vv``): the process
    exits within ``PROMPT_SECONDS`` with the signal's status and one ``error:`` line last,
    before the stage's summary line and without a results table, having estimated few of
    the tensors (the rest cancelled, not run to the end)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(database), "-vv"]
        + ["--prior", "1140,1210,545,360", "--no-focal-search", "--max-triplets", str(TRIPLETS)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_usual_signal_dispositions,
    )
    assert process.stderr is not None
    seen: list[str] = []
    for text in process.stderr:  # until the tensor stage is under way
        seen.append(text)
        if text.startswith("DEBUG colmap_trifocal: triplet "):
            break
    else:
        process.wait(timeout=60)
        pytest.fail(f"no tensor was logged: {''.join(seen[-5:])}")
    os.kill(process.pid, signum)
    start = time.monotonic()
    stdout, rest = process.communicate(timeout=120)
    elapsed = time.monotonic() - start
    stderr = "".join(seen) + rest
    assert elapsed < PROMPT_SECONDS, f"exited {elapsed:.1f} s after the signal"
    assert process.returncode == status, stderr[-2000:]
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == line
    assert f"of {TRIPLETS} triplets gave a tensor" not in stderr  # the stage did not finish
    # The jobs not yet started were cancelled: few tensors were estimated at all.
    estimated = stderr.count("DEBUG colmap_trifocal: triplet ")
    assert estimated < TRIPLETS // 4, f"{estimated} of {TRIPLETS} tensors after the signal"
    assert stdout == ""


def _usual_signal_dispositions() -> None:
    """In the child: SIGINT, SIGTERM and SIGHUP as in a terminal (a test runner may start
    its workers with some ignored, and the command line leaves an ignored signal ignored)."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_DFL)
