"""Outputs (``--json``, ``--png``, WORKSPACE, ``--keep``, ``--output``): none is or holds an
input, each is checked before any work, and pipes and FIFOs never block for good.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import CliResult, run_cli, without_root_file_access

from bad_input.builders import (
    calibrate_model,
    colmap_project,
    copy_good,
    database_and_backup,
    database_in_workspace,
    earlier_demo,
    earlier_demo_workspace,
    good_and_fifo,
    good_and_socket,
    images_and_hard_link,
    images_and_link_to_them,
    images_in_sparse,
    images_linked_into_sparse,
    link_to_database,
    link_to_images_in_sparse,
    make_model,
    model_and_database,
    model_and_fifo,
    model_database_and_empty_output,
    model_database_and_link,
    models_with,
    notes_file,
    run_database,
    three_images,
    two_copies,
    two_databases,
    unwritable_workspace,
    with_companion,
)
from bad_input.table import (
    PARAMS,
    QUICK_READ,
    Case,
    table_test,
)

CASES: dict[str, Case] = {
    "--json into a missing folder": Case(
        copy_good, "does not exist", ("--json", "/nonexistent-folder/result.json")
    ),
    "--json is a folder": Case(copy_good, "/tmp is not a writable file", ("--json", "/tmp")),
    "--json is the database": Case(
        copy_good, "--json", argv=lambda f, p, w: ("calibrate", p, "--json", p)
    ),
    "--json is the database, with --write": Case(
        copy_good,
        "is the database: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", p, "--write"),
    ),
    "--json is a symlink to the database": Case(
        link_to_database("symlink"),
        "(the same file as",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "out.json"),
    ),
    "--json is a hard link to the database": Case(
        link_to_database("hardlink"),
        "(the same file as",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "out.json", "--write"),
    ),
    "run --png is the --database": Case(copy_good, "--png", argv=run_database("--png", "{path}")),
    "show --png is a model file": Case(
        models_with(),
        "is a file of MODEL",
        argv=lambda f, p, w: ("show", p, "--png", p / "images.bin"),
    ),
    "run --png is a file of --model": Case(
        lambda f, g: copy_good(make_model(f).parent.parent, g),
        "is a file of --model",
        argv=run_database(
            "--model", "{folder}/sparse/0", "--png", "{folder}/sparse/0/points3D.bin"
        ),
    ),
    "evaluate --json is a model file": Case(
        models_with(),
        "is a file of the dataset",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--json", p / "points3D.bin"),
    ),
    "calibrate --output not empty": Case(
        lambda f, g: copy_good(make_model(f).parent.parent, g),
        "--output must be a new or empty folder",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", f),
    ),
    "run --database is WORKSPACE/database.db, --overwrite": Case(
        copy_good,
        "is the --database input",
        # IMAGES (only for colours with --database) is not the workspace here.
        argv=lambda f, p, w: ("run", f / "no-images", f, "--database", p, "--overwrite"),
    ),
    "run --model inside WORKSPACE/sparse, --overwrite": Case(
        database_in_workspace,
        "inside the workspace output",
        argv=lambda f, p, w: (
            "run",
            f / "no-images",
            f,
            "--database",
            p,
            "--model",
            f / "sparse" / "0",
            "--overwrite",
        ),
    ),
    "run --png into a missing folder": Case(
        copy_good,
        "cannot write --png",
        argv=lambda f, p, w: ("run", f, w, "--png", f / "missing" / "x.png"),
    ),
    "run IMAGES is WORKSPACE/sparse, --overwrite": Case(
        images_in_sparse,
        "IMAGES",
        argv=lambda f, p, w: ("run", p, f, "--overwrite"),
    ),
    "run IMAGES is WORKSPACE/sparse through ..": Case(
        images_in_sparse,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p / ".." / "sparse", f, "--overwrite"),
    ),
    "run IMAGES is a symlink to WORKSPACE/sparse": Case(
        link_to_images_in_sparse,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, f, "--overwrite"),
    ),
    "run images are symlinks into WORKSPACE/sparse": Case(
        images_linked_into_sparse,
        "is inside the workspace output",
        argv=lambda f, p, w: ("run", p, f / "ws", "--overwrite"),
    ),
    "run --png is an input image": Case(
        lambda f, g: three_images(f / "photos"),
        "/photos/b.png is a file of IMAGES: refusing",
        argv=lambda f, p, w: ("run", p, w, "--png", p / "b.png"),
    ),
    "run --png is a hard link to an input image": Case(
        images_and_hard_link,
        "is a file of IMAGES (the same file as",
        argv=lambda f, p, w: ("run", p, w, "--png", f / "out.png"),
    ),
    "run WORKSPACE is IMAGES, --overwrite": Case(
        lambda f, g: three_images(f / "photos"),
        "is the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, p, "--overwrite"),
    ),
    "run WORKSPACE is a symlink to IMAGES, --overwrite": Case(
        images_and_link_to_them,
        "is the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, f / "link", "--overwrite"),
    ),
    "run WORKSPACE holds IMAGES (a COLMAP project), --overwrite": Case(
        colmap_project,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p / "images", p, "--overwrite"),
    ),
    "run WORKSPACE inside IMAGES": Case(
        lambda f, g: three_images(f / "photos"),
        "is inside the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, p / "workspace"),
    ),
    "calibrate --json is the backup --write makes (two databases)": Case(
        two_databases,
        "is a backup name of the database",
        argv=lambda f, p, w: (
            "calibrate",
            f / "a" / "database.db",
            f / "b" / "database.db",
            "--write",
            "--json",
            f / "a" / "database.db.bak",
        ),
    ),
    "calibrate --json is an earlier backup": Case(
        database_and_backup,
        "is a backup name of the database",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "database.db.bak1"),
    ),
    "demo --keep holds a demo.db": Case(
        earlier_demo,
        "demo.db already exists: refusing to replace it",
        argv=lambda f, p, w: ("demo", "--keep", f),
    ),
    "demo --keep holds a demo workspace": Case(
        earlier_demo_workspace,
        "already exists: refusing to replace it",
        argv=lambda f, p, w: ("demo", "--keep", f),
    ),
    "calibrate --json is a file of --model": Case(
        model_and_database,
        "is a file of --model: refusing",
        argv=calibrate_model("--json", "{folder}/sparse/0/points3D.bin"),
    ),
    "calibrate --json is a symlink to a file of --model": Case(
        model_database_and_link,
        "is a file of --model (the same file as",
        argv=calibrate_model("--json", "{folder}/out.json"),
    ),
    "calibrate --json is the database's -shm": Case(
        with_companion("-shm"),
        "database.db-shm is the database's companion file: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "database.db-shm"),
    ),
    "run --png is the --database's -wal": Case(
        with_companion("-wal"),
        "is the --database input's companion file",
        argv=run_database("--png", "{folder}/database.db-wal"),
    ),
    "run --png is WORKSPACE/report.json": Case(
        lambda f, g: (f / "ws").mkdir() or three_images(f / "photos"),
        "is also the workspace output",
        argv=lambda f, p, w: ("run", p, f / "ws", "--png", f / "ws" / "report.json"),
    ),
    "calibrate --json inside --output": Case(
        model_database_and_empty_output,
        "is inside --output",
        argv=lambda f, p, w: (
            "calibrate",
            p,
            "--model",
            f / "sparse" / "0",
            "--output",
            f / "out",
            "--json",
            f / "out" / "cameras.bin",
        ),  # fmt: skip
    ),
    "show --png into a missing folder": Case(
        models_with(),
        "cannot write --png: folder",
        argv=lambda f, p, w: ("show", p, "--png", w / "view.png"),
    ),
    "show --png in a folder no file can be made in": Case(
        models_with(),
        "cannot write --png: folder /proc is not writable",
        argv=lambda f, p, w: ("show", p, "--png", "/proc/view.png"),
    ),
    "--json in a folder no file can be made in": Case(
        copy_good, "cannot write --json: folder /proc is not writable", ("--json", "/proc/out.json")
    ),
    "calibrate --output in a folder no folder can be made in": Case(
        model_and_database,
        "cannot write --output: folder /proc is not writable",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", "/proc/m"),
    ),
    "synthetic --output is a file": Case(
        notes_file,
        "notes.txt is not a folder",
        argv=lambda f, p, w: ("synthetic", "--runs", "1", "--methods", "direct", "--output", p),
    ),
    "demo --keep is a file": Case(
        notes_file, "cannot write --keep: ", argv=lambda f, p, w: ("demo", "--keep", p)
    ),
    "run WORKSPACE in a folder no folder can be made in": Case(
        lambda f, g: three_images(f / "photos"),
        "cannot write WORKSPACE: folder /proc is not writable",
        argv=lambda f, p, w: ("run", p, "/proc/ws"),
    ),
    "run: workspace without write permission": Case(
        unwritable_workspace,
        "cannot write WORKSPACE: folder",
        argv=lambda f, p, w: ("run", p, f / "ws"),
        preexec_fn=without_root_file_access,
    ),
    "model folder, --json is a file of it": Case(
        models_with(),
        "is a file of MODEL: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", p / "cameras.bin"),
    ),
    "several databases, --json is one of them": Case(
        two_copies,
        "--json",
        argv=lambda f, p, w: ("calibrate", p, f / "other.db", "--json", f / "other.db"),
    ),
    "a glob of databases, --json is one of them": Case(
        two_copies,
        "other.db is the database: refusing",
        argv=lambda f, p, w: ("calibrate", f / "*.db", "--json", f / "other.db"),
    ),
    # ----- issue 37: a FIFO without a reader waits a bounded time (here 0.5 s), then one
    # line; a socket is no output
    "--json is a FIFO nobody reads": Case(
        good_and_fifo,
        "/data/out: no process opened the FIFO for reading within 0.5 s",
        argv=lambda f, p, w: ("calibrate", p, *QUICK_READ, "--json", f / "out"),
        stream_timeout=0.5,
    ),
    "--json is a FIFO nobody reads, several inputs": Case(
        good_and_fifo,
        "no process opened the FIFO for reading within 0.5 s",
        argv=lambda f, p, w: ("calibrate", p, p, *QUICK_READ, "--json", f / "out"),
        stream_timeout=0.5,
    ),
    "show --png is a FIFO nobody reads": Case(
        model_and_fifo,
        "no process opened the FIFO for reading within 0.5 s",
        argv=lambda f, p, w: ("show", p, "--png", f / "out"),
        stream_timeout=0.5,
        rendering=True,
    ),
    "--json is a socket": Case(
        good_and_socket,
        "out is not a writable file (a socket)",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "out"),
    ),
}


test_bad_input = table_test(CASES)


def _table_and_json(stdout: str, stderr: str) -> list[dict]:
    """The JSON (all of stdout) and a check that the results table went to stderr."""
    assert stderr.splitlines()[0].split()[:2] == ["camera", "model"], stderr
    return json.loads(stdout)


@pytest.mark.parametrize("target", ["-", "/dev/stdout"])
def test_json_to_stdout_on_a_pipe(target: str, database_copy: Path) -> None:
    """``--json -`` (and ``/dev/stdout`` on a pipe, which failed after the whole run):
    stdout is the JSON alone, the table goes to stderr (issue 15, item 7)."""
    result = run_cli("calibrate", database_copy, *QUICK_READ, "--json", target)
    assert result.returncode == 0, result.stderr
    (entry,) = _table_and_json(result.stdout, result.stderr)
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PARAMS, rtol=1e-4)


def test_json_to_stdout_redirected_to_a_file(database_copy: Path, tmp_path: Path) -> None:
    """``--json /dev/stdout`` with stdout redirected to a file: the file holds the JSON and
    the table is not lost (it went to stderr; before, the JSON replaced the file)."""
    out = tmp_path / "out.txt"
    with out.open("w") as stream:
        result = subprocess.run(
            [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(database_copy)]
            + [*QUICK_READ, "--json", "/dev/stdout"],
            stdout=stream,
            stderr=subprocess.PIPE,
            text=True,
            timeout=300,
        )
    assert result.returncode == 0, result.stderr
    assert len(_table_and_json(out.read_text(), result.stderr)) == 1


def _reading(fd: int, into: list[bytes]) -> threading.Thread:
    """A thread that reads ``fd`` to its end into ``into`` (the reader of a pipe)."""

    def read() -> None:
        with os.fdopen(fd, "rb") as stream:
            into.append(stream.read())

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def test_json_to_a_pipe_given_as_dev_fd(database_copy: Path) -> None:
    """``--json >(cat > f)``: the shell gives ``/dev/fd/N``, a pipe; its real path names
    no file. The JSON goes down the pipe, exit 0 (before: the whole calibration ran, then
    "cannot write /dev/fd/63", exit 2)."""
    read_end, write_end = os.pipe()
    received: list[bytes] = []
    reader = _reading(read_end, received)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(database_copy)]
            + [*QUICK_READ, "--json", f"/dev/fd/{write_end}"],
            capture_output=True,
            text=True,
            timeout=300,
            pass_fds=(write_end,),
        )
    finally:
        os.close(write_end)
    reader.join(timeout=60)
    assert (done.returncode, done.stderr) == (0, ""), done.stderr
    (entry,) = json.loads(received[0])
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PARAMS, rtol=1e-4)


def test_json_to_stderr_on_a_pipe(database_copy: Path) -> None:
    """``--json /dev/stderr`` with stderr a pipe: the JSON on stderr, the table on stdout,
    exit 0 (before: "cannot write /dev/stderr", exit 2, after the calibration)."""
    result = run_cli("calibrate", database_copy, *QUICK_READ, "--json", "/dev/stderr")
    assert result.returncode == 0, result.stderr
    (entry,) = json.loads(result.stderr)
    assert entry["camera_id"] == 1
    assert result.stdout.split()[:2] == ["camera", "model"]


def test_json_to_stderr_redirected_to_a_file(database_copy: Path, tmp_path: Path) -> None:
    """``--json /dev/stderr 2>err.txt``: the JSON is written through descriptor 2, not as
    a new file renamed over ``err.txt`` (which would cut off what stderr says after it)."""
    err = tmp_path / "err.txt"
    with err.open("w") as stream:
        done = subprocess.run(
            [sys.executable, "-m", "colmap_trifocal.cli", "calibrate", str(database_copy)]
            + [*QUICK_READ, "--json", "/dev/stderr"],
            stdout=subprocess.PIPE,
            stderr=stream,
            text=True,
            timeout=300,
        )
        inode = os.fstat(stream.fileno()).st_ino
    assert done.returncode == 0
    assert err.stat().st_ino == inode  # the same file, not replaced
    assert json.loads(err.read_text())[0]["camera_id"] == 1


def test_json_to_a_fifo_whose_reader_comes_late(
    database_copy: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """A FIFO whose reader opens it a second after the calibration has finished: the
    output waits for it (within the timeout) and the reader gets the whole JSON."""
    fifo = tmp_path / "out"
    os.mkfifo(fifo)
    received: list[bytes] = []

    def read_later() -> None:
        time.sleep(1.0)
        received.append(fifo.read_bytes())

    reader = threading.Thread(target=read_later, daemon=True)
    reader.start()
    result = run_main("calibrate", database_copy, *QUICK_READ, "--json", fifo)
    reader.join(timeout=60)
    assert result.returncode == 0, result.stderr
    assert json.loads(received[0])[0]["camera_id"] == 1


def test_a_reader_that_stops_reading_times_out(tmp_path: Path) -> None:
    """A pipe whose reader never reads: the write waits at most the timeout, then OSError
    (the command says it in one line) instead of blocking for good."""
    from colmap_trifocal.common.streams import StreamOutput

    read_end, write_end = os.pipe()
    try:
        with StreamOutput(f"/dev/fd/{write_end}", timeout=0.3) as stream:
            with pytest.raises(OSError, match="the reader did not read for 0.3 s"):
                stream.write(b"x" * (4 << 20))  # more than a pipe holds
    finally:
        os.close(read_end)
        os.close(write_end)
