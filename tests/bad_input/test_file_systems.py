"""Full disks and file size limits: ``/dev/full``, ``RLIMIT_FSIZE`` in a child process, and
a small tmpfs where the tests run as root. Nothing is left behind.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from conftest import CliResult, assert_one_error_line, run_cli, synthesize

from bad_input.builders import (
    copy_good,
    image_folder,
    run_image_folder,
)
from bad_input.table import (
    QUICK,
    Case,
    limit_file_size,
    listing,
    main_lines,
    sha256,
    table_test,
)
from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.common.files import write_model_atomically
from colmap_trifocal.database import backup as backup_module

CASES: dict[str, Case] = {
    "--json on a full disk": Case(
        copy_good, "cannot write /dev/full: No space left on device", ("--json", "/dev/full")
    ),
    "--json on a full disk with --write": Case(
        copy_good,
        "cannot write /dev/full: No space left on device",
        ("--json", "/dev/full", "--write"),
    ),
    "no space for the temporary copy": Case(
        copy_good, "cannot copy the database to the temporary folder", preexec_fn=limit_file_size()
    ),
    # ----- issue 37: run and demo on a full file system end in one line and leave nothing
    # (pycolmap raised RuntimeError: "No registered database factory succeeded")
    "run onto a full file system": Case(
        image_folder(lambda _: None, good=3),
        "cannot build the database ",
        argv=run_image_folder(),
        preexec_fn=limit_file_size(),
    ),
    "demo --keep onto a full file system": Case(
        copy_good,
        "cannot write the demo database ",
        argv=lambda f, p, w: ("demo", "--keep", w / "new" / "folder"),
        preexec_fn=limit_file_size(),
    ),
}


test_bad_input = table_test(CASES)


def test_no_space_for_the_backup(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """The backup copy fails (ENOSPC): one line, nothing written, the partial .bak removed."""
    before = sha256(database_copy)

    def full_disk(path: Path, target: Path) -> None:
        target.write_bytes(path.read_bytes()[:4096])  # a partial copy, then the disk is full
        raise OSError(28, os.strerror(28), str(target))

    monkeypatch.setattr(backup_module, "_copy_database", full_disk)
    status, lines = main_lines(run_main, "calibrate", database_copy, *QUICK)
    assert status == 2
    assert lines == [
        f"error: cannot back up the database, nothing written: {database_copy} "
        "(No space left on device)"
    ]
    assert sha256(database_copy) == before
    assert listing(database_copy.parent) == ["database.db"]


# --------------------------------------------------------------------------- a small tmpfs


@pytest.fixture
def small_filesystem(tmp_path: Path) -> Iterator[Callable[[int], Path]]:
    """Factory: a tmpfs of the given size in KiB, mounted below ``tmp_path`` (root only:
    skipped where it cannot be mounted), unmounted after the test."""
    mounted: list[Path] = []

    def mount(size_kib: int) -> Path:
        point = tmp_path / f"small{len(mounted)}"
        point.mkdir()
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(point)],
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (root only): {done.stderr.strip()}")
        mounted.append(point)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", str(point)], check=True)


def _fill(folder: Path, leave_kib: int) -> None:
    """Fill the file system of ``folder`` until ``leave_kib`` KiB are free."""
    free = shutil.disk_usage(folder).free - (leave_kib << 10)
    if free > 0:
        (folder / "filler").write_bytes(b"\0" * free)


def test_write_without_room_for_the_backup(
    good_database: Path, small_filesystem: Callable[[int], Path], tmp_path: Path
) -> None:
    """``--write`` on a file system without room for the backup and the write: refused in
    one line before the calibration, nothing made next to the database (before: the
    calibration ran, SQLite made -wal and -shm it could not fill, and they were left)."""
    folder = small_filesystem(1400)
    database = folder / "database.db"
    shutil.copyfile(good_database, database)
    _fill(folder, 20)
    before = sha256(database)
    result = run_cli("calibrate", database, *QUICK)
    assert_one_error_line(result, "no space for a backup of the database and the write")
    assert result.stdout == ""  # refused before the calibration
    assert sha256(database) == before and listing(folder) == ["database.db", "filler"]


def test_run_onto_a_file_system_that_fills_during_extraction(
    small_filesystem: Callable[[int], Path], tmp_path: Path
) -> None:
    """``run`` onto a file system with room for the database but not for its features: the
    disk fills during SIFT extraction, where COLMAP aborts its process (a C++ exception in
    a reader thread: SIGABRT, a glog stack). Extraction runs in a child process, so this
    is one error line, status 2, and nothing left (the workspace was new)."""
    images = image_folder(lambda _: None, good=6)(tmp_path, tmp_path)
    folder = small_filesystem(2000)
    _fill(folder, 400)  # room for a new database, not for the features of 6 images
    result = run_cli("run", images, folder / "ws")
    assert_one_error_line(
        result,
        f"cannot build the database {folder / 'ws' / 'database.db'}: no space left on its "
        "device (stopped, killed by signal 6)",
    )
    assert listing(folder) == ["filler"]


def test_model_on_a_full_file_system_is_not_left_in_part(
    small_filesystem: Callable[[int], Path], tmp_path: Path
) -> None:
    """A model that does not fit: one error that names the folder, and neither the folder
    nor the temporary one it was written into is left (pycolmap raises after writing
    some of the files)."""
    reconstruction = synthesize(tmp_path / "database.db", points=2000)
    folder = small_filesystem(400)
    _fill(folder, 24)
    with pytest.raises(CalibrationError, match=f"cannot write the model to {folder / '0'}: "):
        write_model_atomically(reconstruction, folder / "0")
    assert listing(folder) == ["filler"]


def test_run_database_onto_a_full_file_system(
    good_database: Path, small_filesystem: Callable[[int], Path], tmp_path: Path
) -> None:
    """``run --database`` whose copy does not fit in the workspace: one line that names the
    workspace (not the temporary folder), and no partial copy or workspace left."""
    images = image_folder(lambda _: None, good=3)(tmp_path, tmp_path)
    folder = small_filesystem(400)
    _fill(folder, good_database.stat().st_size // 2048)  # room for half of the copy
    result = run_cli("run", "--database", good_database, images, folder / "ws")
    assert_one_error_line(
        result,
        f"cannot copy the database to {folder / 'ws'} (no space left on the device): "
        f"{good_database}",
    )
    assert listing(folder) == ["filler"]


def test_demo_onto_a_file_system_that_fills_while_it_writes(
    small_filesystem: Callable[[int], Path],
) -> None:
    """``demo --keep`` onto a file system that fills while the demo database is written:
    pycolmap raises, and when that database closes it throws again from a destructor,
    which aborted the process after the error line. Built in a child process, it is one
    error line, status 2, and nothing left."""
    folder = small_filesystem(8000)
    result = run_cli("demo", "--keep", folder / "d")
    assert_one_error_line(
        result, f"cannot write the demo database {folder / 'd' / 'demo.db'}: no space left"
    )
    assert listing(folder) == []
