"""Bad input to the pycolmap workflow: ``apply``'s and ``merge_cameras``' targets,
``calibrate --cameras-txt`` paths, and a command whose pip extra is missing.

The rules of the bad-input table (:mod:`bad_input.table`): the API raises
``CalibrationError`` and changes nothing (a database byte-identical with no backup
next to it, a reconstruction's cameras as they were); the command line prints one line
``error: ...`` and exits with status 2, no traceback, every file below the row's folder
byte-identical and none added. A missing extra is simulated in a child process whose
import of the module fails as it does where it is not installed.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest
from conftest import CliResult, assert_one_error_line, synthesize, synthesize_per_image

from bad_input.table import PARAMS, tree
from bad_input.table import QUICK_READ as QUICK
from colmap_trifocal import (
    CalibrationError,
    CalibrationOptions,
    CameraCalibration,
    calibrate_database,
    merge_cameras,
)


@pytest.fixture(scope="module")
def per_image(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, CameraCalibration]:
    """One SIMPLE_RADIAL camera per image (COLMAP's default), 6 images; its calibration."""
    path = tmp_path_factory.mktemp("per_image") / "database.db"
    synthesize_per_image(path)
    (result,) = calibrate_database(path, CalibrationOptions(max_triplets=3))
    return path, result


# --------------------------------------------------------------------------- apply, merge_cameras

#: A target maker: (folder, the per-image database) -> the target given to apply or merge.
Make = Callable[[Path, Path], Any]


def _copy(folder: Path, good: Path) -> Path:
    target = folder / "database.db"
    target.write_bytes(good.read_bytes())
    return target


def _camera(_folder: Path, _good: Path) -> pycolmap.Camera:
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=1024, height=768, params=[1, 2, 3, 0])


def _text_file(folder: Path, _good: Path) -> Path:
    path = folder / "notes.db"
    path.write_text("not a database\n")
    return path


def _folder(folder: Path, _good: Path) -> Path:
    (folder / "sparse").mkdir()
    return folder / "sparse"


def _edited(sql: str) -> Make:
    """A copy of the database with one SQL statement applied (sqlite3)."""

    def make(folder: Path, good: Path) -> Path:
        import sqlite3

        path = _copy(folder, good)
        con = sqlite3.connect(path)
        con.execute(sql)
        con.commit()
        con.close()
        return path

    return make


def _closed_database(folder: Path, good: Path) -> pycolmap.Database:
    db = pycolmap.Database.open(str(_copy(folder, good)))
    db.close()
    return db


def _open_database(sql: str) -> Make:
    """An open pycolmap.Database of a copy edited with ``sql``."""

    def make(folder: Path, good: Path) -> pycolmap.Database:
        return pycolmap.Database.open(str(_edited(sql)(folder, good)))

    return make


def _reconstruction(edit: Callable[[pycolmap.Reconstruction], None]) -> Make:
    """A reconstruction of the database's cameras (one image each), changed by ``edit``."""

    def make(_folder: Path, good: Path) -> pycolmap.Reconstruction:
        reconstruction = pycolmap.Reconstruction()
        with pycolmap.Database.open(str(good)) as db:
            for camera in db.read_all_cameras():
                reconstruction.add_camera_with_trivial_rig(camera)
        edit(reconstruction)
        return reconstruction

    return make


def _resize_last(reconstruction: pycolmap.Reconstruction) -> None:
    reconstruction.cameras[max(reconstruction.cameras)].width = 2048


def _only_three(_folder: Path, good: Path) -> pycolmap.Reconstruction:
    """Cameras 1, 2, 3 of the 6-camera group: neither the group nor its first camera only."""
    reconstruction = pycolmap.Reconstruction()
    with pycolmap.Database.open(str(good)) as db:
        for camera in db.read_all_cameras()[:3]:
            reconstruction.add_camera_with_trivial_rig(camera)
    return reconstruction


APPLY_CASES: dict[str, tuple[Make, str]] = {
    "None": (lambda f, g: None, "not NoneType"),
    "a pycolmap.Camera": (_camera, "not Camera"),
    "a camera id": (lambda f, g: 1, "not int"),
    "a list of cameras": (lambda f, g: [_camera(f, g)], "not list"),
    "path: missing": (lambda f, g: f / "missing.db", "database not found"),
    "path: a folder (a model)": (_folder, "reads a model folder"),
    "path: not a database": (_text_file, "not an SQLite database"),
    "path: another image size": (
        _edited("UPDATE cameras SET width = 2048 WHERE camera_id = 3"),
        "differs in model or size",
    ),
    "path: another model": (
        _edited("UPDATE cameras SET model = 0"),
        "differs in model or size",
    ),
    "path: a camera of the group missing": (
        _edited("DELETE FROM cameras WHERE camera_id = 4"),
        "has no camera 4",
    ),
    "path: another database (no camera of the group)": (
        _edited("UPDATE cameras SET camera_id = camera_id + 100"),
        "has no camera 1",
    ),
    "pycolmap.Database: closed": (_closed_database, "closed?"),
    "pycolmap.Database: another image size": (
        _open_database("UPDATE cameras SET width = 2048 WHERE camera_id = 2"),
        "camera 2 of the database is a SIMPLE_RADIAL 2048x768",
    ),
    "pycolmap.Database: a camera of the group missing": (
        _open_database("DELETE FROM cameras WHERE camera_id = 5"),
        "has no camera 5",
    ),
    "reconstruction: another image size": (
        _reconstruction(_resize_last),
        "is a SIMPLE_RADIAL 2048x768, the calibrated one a SIMPLE_RADIAL 1024x768",
    ),
    "reconstruction: part of the group": (_only_three, "has no camera 4"),
    "reconstruction: empty": (lambda f, g: pycolmap.Reconstruction(), "has no camera 1"),
}


def _state(target: Any) -> Any:
    """What must not change: a reconstruction's or an open database's camera params."""
    if isinstance(target, pycolmap.Reconstruction):
        return {c: list(camera.params) for c, camera in target.cameras.items()}
    if isinstance(target, pycolmap.Database):
        try:
            return {c.camera_id: list(c.params) for c in target.read_all_cameras()}
        except ValueError:  # closed
            return None
    return None


@pytest.mark.parametrize("name", list(APPLY_CASES))
def test_apply_refuses(
    name: str, per_image: tuple[Path, CameraCalibration], tmp_path: Path
) -> None:
    good, result = per_image
    make, fragment = APPLY_CASES[name]
    target = make(tmp_path, good)
    before, files = _state(target), tree(tmp_path)
    try:
        with pytest.raises(CalibrationError, match=fragment) as raised:
            result.apply(target)
        assert "\n" not in str(raised.value)
        assert _state(target) == before
    finally:
        if isinstance(target, pycolmap.Database):
            target.close()
    if not isinstance(target, pycolmap.Database):  # an open one's files are pycolmap's
        assert tree(tmp_path) == files  # no file changed or added, no backup made


MERGE_CASES: dict[str, tuple[Make, list[int], str]] = {
    "None": (lambda f, g: None, [1, 2], "not NoneType"),
    "a pycolmap.Database": (
        lambda f, g: pycolmap.Database.open(str(_copy(f, g))),
        [1, 2],
        "pass its path",
    ),
    "camera ids as a string": (_copy, "1,2", "must be a list of camera ids"),  # type: ignore[dict-item]
    "no camera ids": (_copy, [], "non-empty list of ints"),
    "database: unknown camera": (_copy, [1, 99], "camera 99 is not in the database"),
    "database: another image size": (
        _edited("UPDATE cameras SET width = 2048 WHERE camera_id = 2"),
        [1, 2, 3],
        "differ in model or image size",
    ),
    "database: missing": (lambda f, g: f / "missing.db", [1, 2], "database not found"),
    "reconstruction: unknown camera": (_reconstruction(lambda r: None), [1, 99], "no camera 99"),
    "reconstruction: another image size": (
        _reconstruction(_resize_last),
        [1, 6],
        "differ in model or image size",
    ),
}


@pytest.mark.parametrize("name", list(MERGE_CASES))
def test_merge_cameras_refuses(
    name: str, per_image: tuple[Path, CameraCalibration], tmp_path: Path
) -> None:
    good, _ = per_image
    make, camera_ids, fragment = MERGE_CASES[name]
    target = make(tmp_path, good)
    before, files = _state(target), tree(tmp_path)
    try:
        with pytest.raises(CalibrationError, match=fragment):
            merge_cameras(target, camera_ids)
        assert _state(target) == before
    finally:
        if isinstance(target, pycolmap.Database):
            target.close()
    if not isinstance(target, pycolmap.Database):
        assert tree(tmp_path) == files


# --------------------------------------------------------------------------- --cameras-txt


@pytest.fixture(scope="module")
def good_database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("good") / "database.db"
    synthesize(path, "PINHOLE", PARAMS)
    return path


@dataclass
class Case:
    """A refused ``calibrate`` command line: (folder, its database) -> the arguments."""

    argv: Callable[[Path, Path], tuple]
    fragment: str
    make: Callable[[Path, Path], None] = lambda folder, database: None


def _model_folder(folder: Path, _database: Path) -> None:
    model = folder / "sparse"
    model.mkdir()
    synthesize(folder / "model.db", "PINHOLE", PARAMS).write(model)
    (folder / "model.db").unlink()


CAMERAS_TXT_CASES = {
    "into a missing folder": Case(
        lambda f, d: (d, "--cameras-txt", f / "missing" / "cameras.txt"),
        "cannot write --cameras-txt: folder",
    ),
    "a folder": Case(lambda f, d: (d, "--cameras-txt", f), "is not a writable file"),
    "the database": Case(lambda f, d: (d, "--cameras-txt", d), "the database: refusing"),
    "a symlink to the database": Case(
        lambda f, d: (d, "--cameras-txt", f / "link.txt"),
        "is the database (the same file as",
        lambda f, d: (f / "link.txt").symlink_to(d),
    ),
    "the database's backup name, with --write": Case(
        lambda f, d: (d, "--write", "--cameras-txt", f / "database.db.bak"),
        "is a backup name of the database",
    ),
    "the database's -wal": Case(
        lambda f, d: (d, "--cameras-txt", f / "database.db-wal"),
        "is the database's companion file: refusing",
        lambda f, d: (f / "database.db-wal").write_bytes(b""),
    ),
    "the same file as --json": Case(
        lambda f, d: (d, "--json", f / "out.txt", "--cameras-txt", f / "out.txt"),
        "out.txt",
    ),
    "standard output twice": Case(
        lambda f, d: (d, "--json", "-", "--cameras-txt", "-"),
        "--json and --cameras-txt cannot both go to standard output",
    ),
    "several inputs": Case(
        lambda f, d: (d, d.with_name("other.db"), "--cameras-txt", f / "cameras.txt"),
        "--cameras-txt takes one database, not several inputs",
        lambda f, d: d.with_name("other.db").write_bytes(d.read_bytes()),
    ),
    "a file of the model folder": Case(
        lambda f, d: (f / "sparse", "--cameras-txt", f / "sparse" / "cameras.bin"),
        "is a file of MODEL",
        _model_folder,
    ),
}


@pytest.mark.parametrize("name", list(CAMERAS_TXT_CASES))
def test_cameras_txt_refused(
    name: str, good_database: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    case = CAMERAS_TXT_CASES[name]
    database = tmp_path / "database.db"
    database.write_bytes(good_database.read_bytes())
    case.make(tmp_path, database)
    before = tree(tmp_path)
    result = run_main("calibrate", *case.argv(tmp_path, database), *QUICK)
    assert_one_error_line(result, case.fragment)
    assert result.stdout == ""
    assert tree(tmp_path) == before


# --------------------------------------------------------------------------- missing extras

#: A child interpreter where importing the named modules fails as if they were not
#: installed (``None`` in ``sys.modules``: ModuleNotFoundError), then the command line.
_WITHOUT = (
    "import sys\n"
    "for name in sys.argv[1].split(','):\n"
    "    sys.modules[name] = None\n"
    "from colmap_trifocal.cli import main\n"
    "raise SystemExit(main(sys.argv[2:]))\n"
)


def run_without(modules: str, *args: object, cwd: Path | None = None) -> CliResult:
    """``colmap-trifocal ARGS`` in a child process where ``modules`` cannot be imported."""
    done = subprocess.run(
        [sys.executable, "-c", _WITHOUT, modules, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
    )
    return CliResult(done.returncode, done.stdout, done.stderr)


EXTRA_CASES = {
    "show without Open3D": (
        "open3d",
        lambda f, d: ("show", f / "sparse", "--png", f / "view.png"),
        "show needs Open3D, which is not installed: pip install 'colmap-trifocal[viz]'",
    ),
    "run --png without Open3D": (
        "open3d",
        lambda f, d: ("run", f / "images", f / "ws", "--database", d, "--png", f / "x.png"),
        "run --png needs Open3D, which is not installed: pip install 'colmap-trifocal[viz]'",
    ),
    "synthetic without matplotlib": (
        "matplotlib",
        lambda f, d: ("synthetic", "--runs", "1", "--output", f / "out"),
        "synthetic needs matplotlib, which is not installed: pip install 'colmap-trifocal[viz]'",
    ),
    "evaluate without matplotlib": (
        "matplotlib",
        lambda f, d: ("evaluate", "strecha", f, "--runs", "1", "--output", f / "out"),
        "needs matplotlib, which is not installed: pip install 'colmap-trifocal[viz]'",
    ),
    "calibrate --dask without Dask": (
        "distributed",
        lambda f, d: ("calibrate", d, "--dask", "tcp://127.0.0.1:1"),
        "--dask needs Dask, which is not installed: pip install 'colmap-trifocal[dask]'",
    ),
    "synthetic --dask without Dask": (
        "distributed",
        lambda f, d: ("synthetic", "--runs", "1", "--output", f / "out", "--dask", "tcp://x:1"),
        "--dask needs Dask, which is not installed: pip install 'colmap-trifocal[dask]'",
    ),
}


@pytest.mark.parametrize("name", list(EXTRA_CASES))
def test_a_missing_extra_is_named_in_one_line(
    name: str, good_database: Path, tmp_path: Path
) -> None:
    modules, argv, fragment = EXTRA_CASES[name]
    database = tmp_path / "database.db"
    database.write_bytes(good_database.read_bytes())
    (tmp_path / "sparse").mkdir()
    synthesize(tmp_path / "model.db", "PINHOLE", PARAMS).write(tmp_path / "sparse")
    (tmp_path / "model.db").unlink()
    before = tree(tmp_path)
    result = run_without(modules, *argv(tmp_path, database))
    assert_one_error_line(result, fragment)
    assert tree(tmp_path) == before


def test_the_demo_needs_no_extra(tmp_path: Path) -> None:
    """README's first command: ``pip install .`` (no extra) and ``demo``."""
    result = run_without("open3d,matplotlib,distributed,dask", "demo")
    assert result.returncode == 0, result.stderr
    assert "mean relative error" in result.stdout
    error = float(result.stdout.strip().splitlines()[-1].split(":")[1].split("%")[0])
    assert error < 0.5


def test_calibrate_needs_no_extra(good_database: Path, tmp_path: Path) -> None:
    """The core install calibrates a database and writes COLMAP's cameras.txt."""
    out = tmp_path / "cameras.txt"
    result = run_without(
        "open3d,matplotlib,distributed,dask",
        "calibrate",
        good_database,
        *QUICK,
        "--cameras-txt",
        out,
    )
    assert result.returncode == 0, result.stderr
    line = out.read_text().splitlines()[-1].split()
    assert line[:4] == ["1", "PINHOLE", "1024", "768"]
    np.testing.assert_allclose([float(v) for v in line[4:]], PARAMS, rtol=1e-3)
