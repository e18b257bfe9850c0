"""Bad input through the command line: one table, one ``error:`` line each, data untouched.

Every row builds its input (with pycolmap where it is a COLMAP database or model), runs
the command line (``calibrate PATH ARGS`` unless the row gives another command: ``run``,
``show``, ``evaluate``, ``synthetic``) and checks: the exit status (2), exactly one
stderr line ``error: ...`` containing the row's fragment, no traceback, every file below
the row's folder byte-identical (sha256) and none added or removed (no ``.bak``, no
``-wal``/``-shm`` left behind), and no ``run`` workspace created. The table had 31 rows
before issue 15, 70 after, and 83 with the rows that were separate tests or assertions
in ``test_cli.py``, ``test_evaluation.py`` and ``test_camera_groups.py`` (issue 24;
``pytest --collect-only -k "test_bad_input["``).

The rows run ``colmap_trifocal.cli.main`` in this process (``conftest.run_main``: file
descriptors captured, so pycolmap's C++ log counts as stderr; signal handlers, logging
and COLMAP's log level restored after each row). A row whose point is the process runs a
subprocess: a file-size limit (``setrlimit``) would bind the test runner itself. A lock
is held by another process: pycolmap has its own SQLite, and POSIX locks taken by
Python's ``sqlite3`` in this process would not bind it.

Ctrl-C (SIGINT), SIGTERM and SIGHUP during ``--write`` are tested twice: by fault
injection in this process (a KeyboardInterrupt or a real signal at each step of the write
path) and by real signals sent to a subprocess at delays spread over its whole run.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import (
    CliResult,
    assert_one_error_line,
    database_rows,
    run_cli,
    synthesize,
    texture_views,
    without_root_file_access,
)

from colmap_trifocal.database import sqlite_files
from colmap_trifocal.database import writing as database_module

PARAMS = [1100.0, 1250.0, 530.0, 370.0]
PRIOR = "1140,1210,545,360"
PRIOR_VALUES = [1140.0, 1210.0, 545.0, 360.0]
#: Enough for the write path to run (fewer triplets, no focal search: faster).
QUICK = ("--prior", PRIOR, "--max-triplets", "3", "--no-focal-search", "--write")
WIDTH, HEIGHT = 1024, 768
Config = pycolmap.TwoViewGeometryConfiguration

# --------------------------------------------------------------------------- helpers


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tree(folder: Path) -> dict[str, str]:
    """Every file below ``folder`` (symlinks as their target's name): its sha256."""
    return {
        str(p.relative_to(folder)): (f"-> {os.readlink(p)}" if p.is_symlink() else sha256(p))
        for p in sorted(folder.rglob("*"))
        if p.is_file() or p.is_symlink()
    }


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


def write_database(
    path: Path,
    keypoints: list[np.ndarray],
    matches: dict[tuple[int, int], np.ndarray],
    model: str = "PINHOLE",
    params: list[float] | None = None,
    config: Config = Config.UNCALIBRATED,
) -> None:
    """A COLMAP database with one camera, one image per keypoint array, the given matches.

    ``matches[(i, j)]`` (1-based image ids) is stored both as raw matches and as the
    inlier matches of a two-view geometry with configuration ``config``.
    """
    with pycolmap.Database.open(str(path)) as db:
        camera = pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT, params=params or PARAMS)
        camera_id = db.write_camera(camera)
        for index, xy in enumerate(keypoints):
            image_id = db.write_image(pycolmap.Image(name=f"image{index}.jpg", camera_id=camera_id))
            db.write_keypoints(image_id, np.asarray(xy, dtype=np.float32))
        for (id1, id2), pairs in matches.items():
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = config
            geometry.inlier_matches = pairs.astype(np.uint32)
            db.write_matches(id1, id2, pairs.astype(np.uint32))
            db.write_two_view_geometry(id1, id2, geometry)


def all_pairs(num_images: int) -> list[tuple[int, int]]:
    return [(a, b) for a in range(1, num_images + 1) for b in range(a + 1, num_images + 1)]


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


def limit_file_size() -> None:
    """In the child: files may not grow beyond 64 KiB (writes fail with EFBIG, like a full disk)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))


# --------------------------------------------------------------------------- the table


@pytest.fixture(scope="module")
def good_database(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 images of one PINHOLE camera, exact keypoints, exhaustive verified matches."""
    path = tmp_path_factory.mktemp("good") / "database.db"
    synthesize(path, "PINHOLE", PARAMS)
    return path


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


def _copy(folder: Path, good: Path) -> Path:
    target = folder / "database.db"
    shutil.copyfile(good, target)
    return target


def _text_file(folder: Path, _good: Path) -> Path:
    path = folder / "notes.db"
    path.write_text("these are my notes, not a database\n" * 20)
    return path


def _empty_file(folder: Path, _good: Path) -> Path:
    path = folder / "empty.db"
    path.touch()
    return path


def _truncated(folder: Path, good: Path) -> Path:
    path = folder / "truncated.db"
    data = good.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _other_tool(folder: Path, _good: Path) -> Path:
    path = folder / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE photos (id INTEGER PRIMARY KEY, path TEXT)")
    con.execute("INSERT INTO photos (path) VALUES ('a.jpg'), ('b.jpg'), ('c.jpg')")
    con.commit()
    con.close()
    return path


def _rollback_journal_copy(folder: Path, good: Path) -> Path:
    """A copy in rollback-journal mode, where an EXCLUSIVE lock also blocks readers."""
    path = _copy(folder, good)
    con = sqlite3.connect(path)
    con.execute("PRAGMA journal_mode=DELETE")
    con.close()
    return path


def _without(*tables: str) -> Callable[[Path, Path], Path]:
    def make(folder: Path, good: Path) -> Path:
        path = _copy(folder, good)
        con = sqlite3.connect(path)
        for table in tables:
            con.execute(f"DELETE FROM {table}")
        con.commit()
        con.close()
        return path

    return make


def _empty_colmap(folder: Path, _good: Path) -> Path:
    path = folder / "new.db"
    pycolmap.Database.open(str(path)).close()
    return path


def _all_degenerate(folder: Path, good: Path) -> Path:
    path = _copy(folder, good)
    with pycolmap.Database.open(str(path)) as db:
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            geometry.config = Config.DEGENERATE
            db.update_two_view_geometry(*pycolmap.pair_id_to_image_pair(pair_id), geometry)
    return path


def _random_keypoints(rng: np.random.Generator, count: int) -> np.ndarray:
    return rng.uniform([0, 0], [WIDTH, HEIGHT], size=(count, 2))


def _random_consistent_matches(folder: Path, _good: Path) -> Path:
    """Matches of random points: 3-cycle consistent (so they form tracks), but no geometry."""
    rng = np.random.default_rng(7)
    tracks = 100
    keypoints = [_random_keypoints(rng, tracks) for _ in range(3)]
    order = [rng.permutation(tracks) for _ in range(3)]  # track -> keypoint in each image
    matches = {(a, b): np.column_stack([order[a - 1], order[b - 1]]) for a, b in all_pairs(3)}
    path = folder / "outliers.db"
    write_database(path, keypoints, matches)
    return path


def _random_inconsistent_matches(folder: Path, _good: Path) -> Path:
    """Random matches: hardly a keypoint matched in one pair is matched alike in the others."""
    rng = np.random.default_rng(8)
    count = 300
    keypoints = [_random_keypoints(rng, count) for _ in range(4)]
    matches = {
        pair: np.column_stack([rng.permutation(count), rng.permutation(count)])
        for pair in all_pairs(4)
    }
    path = folder / "outliers.db"
    write_database(path, keypoints, matches)
    return path


def _synthetic(
    frames: int = 6, model: str = "PINHOLE", params: list[float] | None = None, points: int = 400
):
    def make(folder: Path, _good: Path) -> Path:
        path = folder / "database.db"
        synthesize(path, model, params or PARAMS, frames=frames, points=points)
        return path

    return make


def _identical_images(folder: Path, _good: Path) -> Path:
    """Three copies of one image: the keypoints coincide (zero baseline)."""
    rng = np.random.default_rng(9)
    xy = _random_keypoints(rng, 400)
    identity = np.column_stack([np.arange(400), np.arange(400)])
    path = folder / "copies.db"
    write_database(path, [xy, xy, xy], {pair: identity for pair in all_pairs(3)})
    return path


def _jittered_copies(folder: Path, _good: Path) -> Path:
    """Three copies of one image with 1.5 px of keypoint jitter: no parallax at all."""
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [WIDTH, HEIGHT], size=(300, 2))
    copies = [xy + rng.normal(0.0, 1.5, xy.shape) for _ in range(3)]
    identity = np.column_stack([np.arange(300), np.arange(300)])
    path = folder / "copies.db"
    write_database(path, copies, {pair: identity for pair in all_pairs(3)})
    return path


def _fisheye(folder: Path, _good: Path) -> Path:
    path = folder / "fisheye.db"
    synthesize(path, "OPENCV_FISHEYE", [*PARAMS, 0.01, 0.0, 0.0, 0.0])
    return path


# ----- issue 15: helpers of the rows below


def _blob_edit(sql: str, *values: object) -> Callable[[Path, Path], Path]:
    """A copy of the good database with one UPDATE applied (sqlite3, no pycolmap)."""

    def make(folder: Path, good: Path) -> Path:
        path = _copy(folder, good)
        con = sqlite3.connect(path)
        con.execute(sql, values)
        con.commit()
        con.close()
        return path

    return make


def _keypoint_value(value: float) -> Callable[[Path, Path], Path]:
    """Keypoint 5 of image 1 gets ``value`` as its x coordinate."""

    def make(folder: Path, good: Path) -> Path:
        path = _copy(folder, good)
        con = sqlite3.connect(path)
        rows, cols, blob = con.execute(
            "SELECT rows, cols, data FROM keypoints WHERE image_id = 1"
        ).fetchone()
        xy = np.frombuffer(blob, np.float32).reshape(rows, cols).copy()
        xy[5, 0] = value
        con.execute("UPDATE keypoints SET data = ? WHERE image_id = 1", (xy.tobytes(),))
        con.commit()
        con.close()
        return path

    return make


def _params(*values: float) -> Callable[[Path, Path], Path]:
    return _blob_edit("UPDATE cameras SET params = ?", np.array(values, "<f8").tobytes())


def _link(kind: str) -> Callable[[Path, Path], Path]:
    """A copy of the good database and ``out.json``, a symlink or a hard link to it."""

    def make(folder: Path, good: Path) -> Path:
        path = _copy(folder, good)
        (os.symlink if kind == "symlink" else os.link)(path, folder / "out.json")
        return path

    return make


def _hot_journal(folder: Path, good: Path) -> Path:
    """A database whose writer was killed mid-transaction: a hot ``-journal`` next to it."""
    path = _rollback_journal_copy(folder, good)
    script = (
        "import os, sqlite3, sys\n"
        "con = sqlite3.connect(sys.argv[1], isolation_level=None)\n"
        "con.execute('PRAGMA cache_size=1')\n"
        "con.execute('BEGIN')\n"
        "con.execute('UPDATE keypoints SET data = data')\n"
        "con.execute('UPDATE descriptors SET data = zeroblob(length(data))')\n"
        "os._exit(0)\n"
    )
    subprocess.run([sys.executable, "-c", script, str(path)], check=True)
    assert path.with_name("database.db-journal").stat().st_size > 0
    return path


#: COLMAP's ``kMaxNumImages``: ``pair_id = MAX_NUM_IMAGES * id1 + id2``.
MAX_NUM_IMAGES = 2**31 - 1
#: Gives the verified pair of images 1 and 2 another pair id (the one argument).
_FIRST_PAIR_ID = f"UPDATE two_view_geometries SET pair_id = ? WHERE pair_id = {MAX_NUM_IMAGES + 2}"


def _pair_id(id1: int, id2: int) -> int:
    return MAX_NUM_IMAGES * id1 + id2


_MODEL: dict[str, bytes] = {}


def _model(folder: Path, cut: dict[str, int | None] | None = None, images: bool = True) -> Path:
    """A pycolmap synthetic model in ``folder/sparse/0`` (and ``folder/images`` if asked);
    ``cut[name] = n`` keeps the first n bytes of ``name.bin`` (None: random bytes)."""
    if not _MODEL:
        with tempfile.TemporaryDirectory() as tmp:
            reconstruction = synthesize(Path(tmp) / "model.db", "PINHOLE", PARAMS)
            reconstruction.write(tmp)
            _MODEL.update({p.name: p.read_bytes() for p in Path(tmp).glob("*.bin")})
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    if images:
        (folder / "images").mkdir()
    rng = np.random.default_rng(3)
    for name, data in _MODEL.items():
        size = (cut or {}).get(name.removesuffix(".bin"), len(data))
        data = rng.bytes(5000) if size is None else data[:size]
        (model / name).write_bytes(data)
    return model


def _models(cut: dict[str, int | None] | None = None, images: bool = True):
    return lambda folder, _good: _model(folder, cut, images)


def _run(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``run IMAGES WORKSPACE --database PATH ARGS`` (the folder as IMAGES)."""
    return lambda folder, path, workspace: ("run", folder, workspace, "--database", path, *args)


def _model_of_other_images(folder: Path, good: Path) -> Path:
    """The good database, and in ``folder/sparse/0`` a model of the same camera and image
    size whose images have other names (another database's)."""
    model = _model(folder, images=False)
    reconstruction = pycolmap.Reconstruction(model)
    for image in reconstruction.images.values():
        image.name = f"other_{image.name}"
    reconstruction.write(model)
    return _copy(folder, good)


def _database_in_workspace(folder: Path, good: Path) -> Path:
    """An earlier run's workspace (the folder) with a model in sparse/0; the database in
    another folder of it."""
    _model(folder, images=False)
    (folder / "input").mkdir()
    return _copy(folder / "input", good)


def _images(folder: Path, names: tuple[str, ...] = ("a.png", "b.png", "c.png")) -> Path:
    """``folder`` with three small readable images (random grey levels, 64 x 48 pixels)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(11)
    for name in names:
        assert cv2.imwrite(str(folder / name), rng.integers(0, 256, (48, 64), np.uint8))
    return folder


def _images_and_link_to_them(folder: Path, _good: Path) -> Path:
    """An image folder ``photos`` and a symlink ``link`` to it."""
    images = _images(folder / "photos")
    (folder / "link").symlink_to(images)
    return images


def _colmap_project(folder: Path, good: Path) -> Path:
    """A COLMAP project: ``project/images`` and the user's own ``project/database.db``."""
    _images(folder / "project" / "images")
    shutil.copyfile(good, folder / "project" / "database.db")
    return folder / "project"


def _two_databases(folder: Path, good: Path) -> Path:
    """``a/database.db`` and ``b/database.db``, copies of the good database."""
    for name in ("a", "b"):
        (folder / name).mkdir()
        shutil.copyfile(good, folder / name / "database.db")
    return folder / "a" / "database.db"


def _database_and_backup(folder: Path, good: Path) -> Path:
    """The good database and an earlier write's backup ``database.db.bak1``."""
    shutil.copyfile(good, folder / "database.db.bak1")
    return _copy(folder, good)


def _earlier_demo(folder: Path, good: Path) -> Path:
    """A folder where an earlier ``demo --keep`` left ``demo.db`` (here: another database)."""
    shutil.copyfile(good, folder / "demo.db")
    return folder / "demo.db"


def _earlier_demo_workspace(folder: Path, good: Path) -> Path:
    """A folder where an earlier ``demo --keep`` left its workspace ``demo/``."""
    (folder / "demo").mkdir()
    shutil.copyfile(good, folder / "demo" / "database.db")
    return folder / "demo" / "database.db"


def _images_in_sparse(folder: Path, _good: Path) -> Path:
    """An earlier run's workspace (the folder) whose ``sparse/`` also holds the images."""
    return _images(folder / "sparse")


def _images_linked_into_sparse(folder: Path, _good: Path) -> Path:
    """An image folder whose images are symlinks to files in the ``sparse/`` of an earlier
    run's workspace ``ws``."""
    _images(folder / "ws" / "sparse")
    (folder / "photos").mkdir()
    for name in ("a.png", "b.png", "c.png"):
        (folder / "photos" / name).symlink_to(folder / "ws" / "sparse" / name)
    return folder / "photos"


def _link_to_images_in_sparse(folder: Path, good: Path) -> Path:
    """``folder/photos``, a symlink to the workspace's ``sparse/`` that holds the images."""
    _images_in_sparse(folder, good)
    (folder / "photos").symlink_to(folder / "sparse")
    return folder / "photos"


def _images_and_hard_link(folder: Path, _good: Path) -> Path:
    """``folder/photos`` with three images, ``folder/out.png`` a hard link to one of them."""
    photos = _images(folder / "photos")
    os.link(photos / "a.png", folder / "out.png")
    return photos


def _with_companion(suffix: str) -> Callable[[Path, Path], Path]:
    """A copy of the good database with a companion file (``-shm``, ``-wal``) beside it."""

    def make(folder: Path, good: Path) -> Path:
        path = _copy(folder, good)
        path.with_name(path.name + suffix).write_bytes(b"\0" * 32768)
        return path

    return make


# ----- issue 22: the image folder and the workspace of ``run``


def _encoded(suffix: str, image: np.ndarray, *params: int) -> bytes:
    ok, data = cv2.imencode(suffix, image, list(params))
    assert ok
    return data.tobytes()


def _image_folder(add: Callable[[Path], object], good: int = 2) -> Callable[[Path, Path], Path]:
    """An image folder ``folder/images``: ``good`` JPEGs, then ``add(images)`` puts the bad
    file(s) in."""

    def make(folder: Path, _good: Path) -> Path:
        images = folder / "images"
        images.mkdir()
        for index, image in enumerate(texture_views(good)):
            (images / f"{index:02d}.jpg").write_bytes(_encoded(".jpg", image))
        add(images)
        return images

    return make


def _model_and_database(folder: Path, good: Path) -> Path:
    """A model in ``folder/sparse/0`` and the database at ``folder/database.db``."""
    return _copy(_model(folder).parent.parent, good)


def _model_database_and_link(folder: Path, good: Path) -> Path:
    """As :func:`_model_and_database`, with ``folder/out.json`` a symlink to a model file."""
    path = _model_and_database(folder, good)
    (folder / "out.json").symlink_to(folder / "sparse" / "0" / "images.bin")
    return path


def _model_database_and_empty_output(folder: Path, good: Path) -> Path:
    """As :func:`_model_and_database`, with an empty folder ``folder/out``."""
    path = _model_and_database(folder, good)
    (folder / "out").mkdir()
    return path


def _calibrate_model(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``calibrate PATH --model FOLDER/sparse/0 --output WORKSPACE ARGS``."""
    return lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", w, *args)


def _file(folder: Path, _good: Path) -> Path:
    path = folder / "notes.txt"
    path.write_text("mine\n")
    return path


def _write(name: str, data: bytes) -> Callable[[Path], object]:
    return lambda images: (images / name).write_bytes(data)


def _cut(name: str, data: bytes, keep: float = 0.5) -> Callable[[Path], object]:
    """``name`` holding the first ``keep`` share of ``data`` (a truncated download)."""
    return _write(name, data[: int(len(data) * keep)])


def _socket(images: Path) -> None:
    import socket

    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(images / "x.png"))  # the socket file stays after the close


def _run_image_folder(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``run IMAGES WORKSPACE ARGS`` on the made image folder."""
    return lambda folder, path, workspace: ("run", path, workspace, *args)


def _unwritable_workspace(folder: Path, good: Path) -> Path:
    """Three good images and an existing, empty workspace ``folder/ws`` without write
    permission (chmod 555)."""
    images = _image_folder(lambda _: None, good=3)(folder, good)
    (folder / "ws").mkdir(mode=0o555)
    (folder / "ws").chmod(0o555)
    return images


_JPEG = _encoded(".jpg", texture_views(1)[0])
_PROGRESSIVE_JPEG = _encoded(".jpg", texture_views(1)[0], cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
_PNG16 = _encoded(".png", texture_views(1)[0].astype(np.uint16) * 257)


# ----- issue 23: calibrate MODEL_DIR and several inputs


def _only_cameras_bin(folder: Path, _good: Path) -> Path:
    """A model folder holding only ``cameras.bin``."""
    model = _model(folder)
    for name in ("images.bin", "points3D.bin"):
        (model / name).unlink()
    return model


def _two_image_model(folder: Path, _good: Path) -> Path:
    """A model of 2 registered images (their tracks give no triplet)."""
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "model.db", "PINHOLE", PARAMS, frames=2).write(model)
    return model


def _two_copies(folder: Path, good: Path) -> Path:
    """``folder/database.db`` and ``folder/other.db``: two copies of the good database."""
    shutil.copyfile(good, folder / "other.db")
    return _copy(folder, good)


CASES: dict[str, Case] = {
    "missing path": Case(lambda folder, _: folder / "nope.db", "database not found"),
    "directory": Case(lambda folder, _: folder, "is a directory"),
    "text file named .db": Case(_text_file, "not an SQLite database"),
    "empty file": Case(_empty_file, "not an SQLite database"),
    "truncated SQLite": Case(_truncated, "truncated or corrupt"),
    "locked (exclusive, rollback journal)": Case(
        _rollback_journal_copy, "locked by another process", lock=("BEGIN EXCLUSIVE", None)
    ),
    "locked (immediate) with --write": Case(
        _copy,
        "locked by another process",
        args=("--prior", PRIOR, "--write"),
        lock=("BEGIN IMMEDIATE", None),
    ),
    "another tool's SQLite": Case(_other_tool, "not a COLMAP database (no table cameras"),
    "COLMAP database without images": Case(_empty_colmap, "database has no images"),
    "images without keypoints": Case(
        _without("keypoints", "descriptors", "matches", "two_view_geometries"),
        "database has no keypoints (run COLMAP feature extraction first)",
    ),
    "keypoints without matches": Case(
        _without("matches", "two_view_geometries"),
        "no verified matches (run COLMAP feature matching first)",
    ),
    "matches never verified": Case(
        _without("two_view_geometries"), "15 image pairs have raw matches"
    ),
    "all pairs DEGENERATE": Case(
        _all_degenerate, "of 15 verified image pairs 15 are DEGENERATE or WATERMARK"
    ),
    "outlier matches, no consistent triplet": Case(
        _random_inconsistent_matches, "no image triplet with at least 30 three-view tracks"
    ),
    "outlier matches, no consistent tensor": Case(
        _random_consistent_matches, "no triplet gave a consistent trifocal tensor"
    ),
    # from test_cli.py: a good scene of 30 points, too few three-view tracks
    "20 points, no triplet": Case(
        _synthetic(points=20), "no image triplet with at least 30 three-view tracks"
    ),
    "single image": Case(_synthetic(1), "database has only 1 image, at least 3"),
    "two images": Case(_synthetic(2), "database has only 2 images, at least 3"),
    "identical images": Case(_identical_images, "3 are duplicates (the matched keypoints coincide"),
    "fisheye camera": Case(_fisheye, "fisheye camera model OPENCV_FISHEYE is not supported"),
    "unknown camera id": Case(_copy, "camera id 7 is not in the database", ("--camera-id", "7")),
    "NaN prior": Case(_copy, "must be finite", ("--prior", "nan,1250,530,370")),
    "zero prior": Case(_copy, "focal lengths positive", ("--prior", "0,1250,530,370")),
    "prior of 3 values": Case(_copy, "expected 4 values FX,FY,CX,CY, got 3", ("--prior", "1,2,3")),
    "prior of 5 values": Case(
        _copy, "expected 4 values FX,FY,CX,CY, got 5", ("--prior", "1,2,3,4,5")
    ),
    "prior not numbers": Case(_copy, "expected four numbers", ("--prior", "a,b,c,d")),
    "unknown --method": Case(_copy, "--method: invalid choice: 'magic'", ("--method", "magic")),
    "read-only database with --write": Case(
        _copy, "cannot write to read-only database", ("--write",), read_only=True
    ),
    "--json on a full disk": Case(
        _copy, "cannot write /dev/full: No space left on device", ("--json", "/dev/full")
    ),
    # The JSON is written before the database: its failure leaves the database alone.
    "--json on a full disk with --write": Case(
        _copy,
        "cannot write /dev/full: No space left on device",
        ("--json", "/dev/full", "--write"),
    ),
    "--json into a missing folder": Case(
        _copy, "does not exist", ("--json", "/nonexistent-folder/result.json")
    ),
    "--json is a folder": Case(_copy, "/tmp is not a writable file", ("--json", "/tmp")),
    "no space for the temporary copy": Case(
        _copy, "cannot copy the database to the temporary folder", preexec_fn=limit_file_size
    ),
    # ----- issue 15, item 2: an output that is the input database
    "--json is the database": Case(
        _copy, "--json", argv=lambda f, p, w: ("calibrate", p, "--json", p)
    ),
    "--json is the database, with --write": Case(
        _copy,
        "is the database: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", p, "--write"),
    ),
    "--json is a symlink to the database": Case(
        _link("symlink"),
        "(the same file as",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "out.json"),
    ),
    "--json is a hard link to the database": Case(
        _link("hardlink"),
        "(the same file as",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "out.json", "--write"),
    ),
    "run --png is the --database": Case(_copy, "--png", argv=_run("--png", "{path}")),
    "show --png is a model file": Case(
        _models(), "is a file of MODEL", argv=lambda f, p, w: ("show", p, "--png", p / "images.bin")
    ),
    "run --png is a file of --model": Case(
        lambda f, g: _copy(_model(f).parent.parent, g),
        "is a file of --model",
        argv=_run("--model", "{folder}/sparse/0", "--png", "{folder}/sparse/0/points3D.bin"),
    ),
    "evaluate --json is a model file": Case(
        _models(),
        "is a file of the dataset",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--json", p / "points3D.bin"),
    ),
    # ----- from test_camera_groups.py: calibrate --model
    "calibrate --output not empty": Case(
        lambda f, g: _copy(_model(f).parent.parent, g),
        "--output must be a new or empty folder",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", f),
    ),
    "calibrate --model without --output": Case(
        lambda f, g: _copy(_model(f).parent.parent, g),
        "--model and --output go together",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0"),
    ),
    "calibrate --refine-distortion without --model": Case(
        _copy, "--refine and --refine-distortion need --model", ("--refine-distortion",)
    ),
    # ----- item 3: run never deletes its inputs
    "run --database is WORKSPACE/database.db, --overwrite": Case(
        _copy,
        "is the --database input",
        # IMAGES (only for colours with --database) is not the workspace here.
        argv=lambda f, p, w: ("run", f / "no-images", f, "--database", p, "--overwrite"),
    ),
    "run --model inside WORKSPACE/sparse, --overwrite": Case(
        _database_in_workspace,
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
    # ----- item 5: tracebacks that become one line
    "keypoint NaN": Case(_keypoint_value(np.nan), "keypoint(s) of image 1"),
    "keypoint inf": Case(_keypoint_value(np.inf), "are NaN or infinite"),
    "keypoints with a negative row count": Case(
        _blob_edit("UPDATE keypoints SET rows = -5 WHERE image_id = 1"),
        "corrupt database: keypoints",
    ),
    "stored params NaN": Case(_params(np.nan, 1250, 530, 370), "stored params (nan,"),
    "stored fx = fy = 0": Case(_params(0, 0, 530, 370), "give --prior or --no-prior"),
    "prior of 1e-300": Case(
        _copy, "invalid starting intrinsics from --prior", ("--prior", "1e-300,1e-300,530,370")
    ),
    "prior principal point 1e308": Case(
        _copy, "principal point within", ("--prior", "525,525,1e308,-1e308")
    ),
    "0x0 camera with --no-prior": Case(
        _blob_edit("UPDATE cameras SET width = 0, height = 0"), "image size of 0x0", ("--no-prior",)
    ),
    "--seed -1": Case(_copy, "seed must be in [0,", ("--seed", "-1")),
    "run --model missing": Case(
        _copy, "model folder not found", argv=_run("--model", "{folder}/nope")
    ),
    "run --model is a file": Case(_copy, "model folder not found", argv=_run("--model", "{path}")),
    "run --model garbage": Case(
        lambda f, g: _copy(_model(f, {"points3D": None}).parent.parent, g),
        "COLMAP model file",
        argv=_run("--model", "{folder}/sparse/0"),
    ),
    "run --camera-model FOO": Case(
        _copy,
        "--camera-model: invalid choice: 'FOO'",
        argv=lambda f, p, w: ("run", f, w, "--camera-model", "FOO"),
    ),
    "run --seed -1": Case(_copy, "seed must be", argv=_run("--seed", "-1")),
    "run --png into a missing folder": Case(
        _copy,
        "cannot write --png",
        argv=lambda f, p, w: ("run", f, w, "--png", f / "missing" / "x.png"),
    ),
    "show: missing model": Case(
        _copy, "model folder not found", argv=lambda f, p, w: ("show", f / "nope")
    ),
    "show: truncated images.bin": Case(
        _models({"images": 3000}),
        "truncated COLMAP model file",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "evaluate colmap: garbage points3D.bin": Case(
        _models({"points3D": None}),
        "points3D.bin",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--runs", "1"),
    ),
    "evaluate colmap: no ../../images": Case(
        _models(images=False),
        ": image folder",
        argv=lambda f, p, w: ("evaluate", "colmap", p, "--runs", "1"),
    ),
    # from test_evaluation.py (the --output folder is the workspace: it must stay absent)
    "evaluate: missing dataset folder": Case(
        _copy,
        "does not exist",
        argv=lambda f, p, w: ("evaluate", "strecha", f / "nope", "--output", w),
    ),
    "evaluate --perturbation a-b": Case(
        _copy,
        "malformed --perturbation",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--perturbation", "a-b", "--output", w),
    ),
    "evaluate --methods magic": Case(
        _copy,
        "unknown method",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--methods", "magic", "--output", w),
    ),
    "evaluate --images 2": Case(
        _copy,
        "at least 3 images",
        argv=lambda f, p, w: ("evaluate", "strecha", f, "--images", "2", "--output", w),
    ),
    "synthetic --noise x": Case(
        _copy,
        "malformed --noise",
        argv=lambda f, p, w: ("synthetic", "--noise", "x", "--output", w),
    ),
    "synthetic --runs 0": Case(
        _copy,
        "--runs must be at least 1",
        argv=lambda f, p, w: ("synthetic", "--runs", "0", "--output", w),
    ),
    "synthetic --seed -1": Case(
        _copy, "seed must be", argv=lambda f, p, w: ("synthetic", "--seed", "-1")
    ),
    "synthetic --noise nan": Case(
        _copy, "invalid --noise 'nan'", argv=lambda f, p, w: ("synthetic", "--noise", "nan")
    ),
    "synthetic --perturbation nan": Case(
        _copy,
        "expected a finite number",
        argv=lambda f, p, w: ("synthetic", "--perturbation", "nan"),
    ),
    "synthetic --perturbation -500": Case(
        _copy, "[0, 100) percent", argv=lambda f, p, w: ("synthetic", "--perturbation", "-500")
    ),
    # ----- item 6: models whose counts do not match their size (pycolmap grew without bound)
    "show: empty points3D.bin": Case(
        _models({"points3D": 0}),
        "(0 bytes)",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "show: truncated points3D.bin": Case(
        _models({"points3D": 20000}),
        "need 39608 bytes, the file has 20000",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    "show: points3D.bin with its count only": Case(
        _models({"points3D": 8}),
        "the file has 8",
        argv=lambda f, p, w: ("show", p, "--png", f / "x.png"),
    ),
    # ----- item 8: one line means one line
    "newline in the path": Case(
        lambda f, _: f / "new\nline.db",
        "data/new\\nline.db",  # escaped: backslash, n
    ),
    "RuntimeWarning: --prior 1e308": Case(
        _copy, "invalid starting intrinsics", ("--prior", "1e308,1e308,530,370")
    ),
    "RuntimeWarning: stored focal 1e300": Case(
        _params(1e300, 1e300, 530, 370), "from the stored camera"
    ),
    "0x0 camera (exit 0 before)": Case(
        _blob_edit("UPDATE cameras SET width = 0, height = 0"), "image size of 0x0"
    ),
    "hot rollback journal": Case(_hot_journal, "hot rollback journal"),
    # ----- issue 22, items 1-3: no output is or holds an input (one rule, every command)
    "run IMAGES is WORKSPACE/sparse, --overwrite": Case(
        _images_in_sparse,
        "IMAGES",
        argv=lambda f, p, w: ("run", p, f, "--overwrite"),
    ),
    "run IMAGES is WORKSPACE/sparse through ..": Case(
        _images_in_sparse,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p / ".." / "sparse", f, "--overwrite"),
    ),
    "run IMAGES is a symlink to WORKSPACE/sparse": Case(
        _link_to_images_in_sparse,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, f, "--overwrite"),
    ),
    "run images are symlinks into WORKSPACE/sparse": Case(
        _images_linked_into_sparse,
        "is inside the workspace output",
        argv=lambda f, p, w: ("run", p, f / "ws", "--overwrite"),
    ),
    "run --png is an input image": Case(
        lambda f, g: _images(f / "photos"),
        "/photos/b.png is a file of IMAGES: refusing",
        argv=lambda f, p, w: ("run", p, w, "--png", p / "b.png"),
    ),
    "run --png is a hard link to an input image": Case(
        _images_and_hard_link,
        "is a file of IMAGES (the same file as",
        argv=lambda f, p, w: ("run", p, w, "--png", f / "out.png"),
    ),
    # ----- issue 37, data loss: no output replaces an input, its backup, or a user's files
    "run WORKSPACE is IMAGES, --overwrite": Case(
        lambda f, g: _images(f / "photos"),
        "is the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, p, "--overwrite"),
    ),
    "run WORKSPACE is a symlink to IMAGES, --overwrite": Case(
        _images_and_link_to_them,
        "is the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, f / "link", "--overwrite"),
    ),
    "run WORKSPACE holds IMAGES (a COLMAP project), --overwrite": Case(
        _colmap_project,
        "holds the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p / "images", p, "--overwrite"),
    ),
    "run WORKSPACE inside IMAGES": Case(
        lambda f, g: _images(f / "photos"),
        "is inside the image folder (IMAGES",
        argv=lambda f, p, w: ("run", p, p / "workspace"),
    ),
    "calibrate --json is the backup --write makes (two databases)": Case(
        _two_databases,
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
        _database_and_backup,
        "is a backup name of the database",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "database.db.bak1"),
    ),
    "demo --keep holds a demo.db": Case(
        _earlier_demo,
        "demo.db already exists: refusing to replace it",
        argv=lambda f, p, w: ("demo", "--keep", f),
    ),
    "demo --keep holds a demo workspace": Case(
        _earlier_demo_workspace,
        "already exists: refusing to replace it",
        argv=lambda f, p, w: ("demo", "--keep", f),
    ),
    "calibrate --json is a file of --model": Case(
        _model_and_database,
        "is a file of --model: refusing",
        argv=_calibrate_model("--json", "{folder}/sparse/0/points3D.bin"),
    ),
    "calibrate --json is a symlink to a file of --model": Case(
        _model_database_and_link,
        "is a file of --model (the same file as",
        argv=_calibrate_model("--json", "{folder}/out.json"),
    ),
    "calibrate --json is the database's -shm": Case(
        _with_companion("-shm"),
        "database.db-shm is the database's companion file: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", f / "database.db-shm"),
    ),
    "run --png is the --database's -wal": Case(
        _with_companion("-wal"),
        "is the --database input's companion file",
        argv=_run("--png", "{folder}/database.db-wal"),
    ),
    "run --png is WORKSPACE/report.json": Case(
        lambda f, g: (f / "ws").mkdir() or _images(f / "photos"),
        "is also the workspace output",
        argv=lambda f, p, w: ("run", p, f / "ws", "--png", f / "ws" / "report.json"),
    ),
    "calibrate --json inside --output": Case(
        _model_database_and_empty_output,
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
    "DATABASE is ., with --json": Case(
        _copy,
        "database path is a directory: .",
        argv=lambda f, p, w: ("calibrate", ".", "--json", f / "out.json"),
    ),
    # ----- issue 22, item 12: output paths checked before any work, so one line
    "show --png into a missing folder": Case(
        _models(),
        "cannot write --png: folder",
        argv=lambda f, p, w: ("show", p, "--png", w / "view.png"),
    ),
    "show --png in a folder no file can be made in": Case(
        _models(),
        "cannot write --png: folder /proc is not writable",
        argv=lambda f, p, w: ("show", p, "--png", "/proc/view.png"),
    ),
    "--json in a folder no file can be made in": Case(
        _copy, "cannot write --json: folder /proc is not writable", ("--json", "/proc/out.json")
    ),
    "calibrate --output in a folder no folder can be made in": Case(
        _model_and_database,
        "cannot write --output: folder /proc is not writable",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", "/proc/m"),
    ),
    "synthetic --output is a file": Case(
        _file,
        "notes.txt is not a folder",
        argv=lambda f, p, w: ("synthetic", "--runs", "1", "--methods", "direct", "--output", p),
    ),
    "demo --keep is a file": Case(
        _file, "cannot write --keep: ", argv=lambda f, p, w: ("demo", "--keep", p)
    ),
    "run WORKSPACE in a folder no folder can be made in": Case(
        lambda f, g: _images(f / "photos"),
        "cannot write WORKSPACE: folder /proc is not writable",
        argv=lambda f, p, w: ("run", p, "/proc/ws"),
    ),
    # ----- issue 22: the image folder of ``run`` (unusable files are skipped, as COLMAP
    # skips them; fewer than 3 usable images is the error, naming the skipped files)
    "run: non-UTF-8 image name": Case(
        _image_folder(
            _write(os.fsdecode(b"caf\xe9.png"), _encoded(".png", texture_views(1)[0])), good=3
        ),
        "/data/images/caf\\xe9.png (COLMAP stores image names as UTF-8",
        argv=_run_image_folder(),
    ),
    "run: 1x1 image": Case(
        _image_folder(_write("x.png", _encoded(".png", np.zeros((1, 1), np.uint8)))),
        "x.png: 1 x 1 px: sides under 8 px",
        argv=_run_image_folder(),
    ),
    "run: 20000x1 image": Case(
        _image_folder(_write("x.png", _encoded(".png", np.zeros((1, 20000), np.uint8)))),
        "x.png: 20000 x 1 px",
        argv=_run_image_folder(),
    ),
    "run: 3000x30 image with --max-image-size 100": Case(
        _image_folder(_write("x.tif", _encoded(".tif", np.zeros((30, 3000), np.uint8)))),
        "3000 x 30 px, 100 x 1 px once downscaled",
        argv=_run_image_folder("--max-image-size", "100"),
    ),
    "run: FIFO named x.png": Case(
        _image_folder(lambda images: os.mkfifo(images / "x.png")),
        "x.png: not a regular file (a FIFO)",
        argv=_run_image_folder(),
    ),
    "run: socket named x.png": Case(
        _image_folder(_socket), "x.png: not a regular file (a socket)", argv=_run_image_folder()
    ),
    "run: symlink to a device": Case(
        _image_folder(lambda images: os.symlink("/dev/null", images / "x.jpg")),
        "x.jpg: not a regular file (a character device)",
        argv=_run_image_folder(),
    ),
    "run: folder named x.jpg": Case(
        _image_folder(lambda images: (images / "x.jpg").mkdir()),
        "x.jpg: not a regular file (a folder)",
        argv=_run_image_folder(),
    ),
    "run: symlink loop": Case(
        _image_folder(lambda images: os.symlink("x.jpg", images / "x.jpg")),
        "x.jpg: a symlink loop",
        argv=_run_image_folder(),
    ),
    "run: dangling symlink": Case(
        _image_folder(lambda images: os.symlink("gone.jpg", images / "x.jpg")),
        "x.jpg: a dangling symlink",
        argv=_run_image_folder(),
    ),
    "run: truncated JPEG": Case(
        _image_folder(_cut("x.jpg", _JPEG)), "x.jpg: truncated JPEG", argv=_run_image_folder()
    ),
    "run: truncated progressive JPEG": Case(
        _image_folder(_cut("x.jpg", _PROGRESSIVE_JPEG, 0.9)),
        "x.jpg: truncated JPEG",
        argv=_run_image_folder(),
    ),
    "run: JPEG without its last byte": Case(
        _image_folder(_write("x.jpg", _JPEG[:-1])),
        "x.jpg: truncated JPEG",
        argv=_run_image_folder(),
    ),
    "run: truncated 16-bit PNG": Case(
        _image_folder(_cut("x.png", _PNG16, 0.8)), "x.png: truncated PNG", argv=_run_image_folder()
    ),
    "run: truncated BMP": Case(
        _image_folder(_cut("x.bmp", _encoded(".bmp", texture_views(1)[0]), 0.9)),
        "x.bmp: truncated BMP",
        argv=_run_image_folder(),
    ),
    "run: truncated float TIFF": Case(
        _image_folder(
            _cut("x.tif", _encoded(".tif", texture_views(1)[0].astype(np.float32) / 255))
        ),
        "x.tif: not an image COLMAP can decode",
        argv=_run_image_folder(),
    ),
    "run: empty image file": Case(
        _image_folder(_write("x.png", b"")), "x.png: empty file", argv=_run_image_folder()
    ),
    "run: text named x.jpg": Case(
        _image_folder(_write("x.jpg", b"not a jpeg\n")),
        "x.jpg: not an image COLMAP can decode",
        argv=_run_image_folder(),
    ),
    "run: no usable image": Case(
        _image_folder(
            lambda images: [
                os.mkfifo(images / "a.png"),
                (images / "b.jpg").write_bytes(_JPEG[:-2]),
                (images / "c.png").write_bytes(b""),
                (images / "d.tif").write_bytes(b"II*\x00"),
                os.symlink("d.tif", images / "e.jpg"),
            ],
            good=0,
        ),
        "has 0 usable image(s); at least 3 are needed (5 skipped: a.png: not a regular file "
        "(a FIFO); b.jpg: truncated JPEG (no end-of-image marker); c.png: empty file; and 2 more)",
        argv=_run_image_folder(),
    ),
    "run: unreadable image (chmod 000)": Case(
        _image_folder(lambda _: None, good=3),
        "02.jpg: cannot be read (Permission denied)",
        argv=_run_image_folder(),
        preexec_fn=without_root_file_access,
        unreadable="images/02.jpg",
    ),
    # ----- issue 22: the workspace and the numbers of ``run``, checked before any folder
    "run: workspace without write permission": Case(
        _unwritable_workspace,
        "cannot write WORKSPACE: folder",
        argv=lambda f, p, w: ("run", p, f / "ws"),
        preexec_fn=without_root_file_access,
    ),
    "run --max-image-size 2147483648": Case(
        _image_folder(lambda _: None, good=3),
        "--max-image-size: must be in [100, 2147483647], got 2147483648",
        argv=_run_image_folder("--max-image-size", "2147483648"),
    ),
    "run --max-image-size 99": Case(
        _image_folder(lambda _: None, good=3),
        "--max-image-size: must be in [100,",
        argv=_run_image_folder("--max-image-size", "99"),
    ),
    "run --max-image-size -1": Case(
        _image_folder(lambda _: None, good=3),
        "--max-image-size: must be in",
        argv=_run_image_folder("--max-image-size=-1"),
    ),
    "run --max-image-size 1600.5": Case(
        _image_folder(lambda _: None, good=3),
        "--max-image-size: expected an integer, got '1600.5'",
        argv=_run_image_folder("--max-image-size", "1600.5"),
    ),
    # ----- issue 22: what COLMAP itself would refuse
    "verified pair of image id 2**31 - 1": Case(
        _blob_edit(_FIRST_PAIR_ID, _pair_id(MAX_NUM_IMAGES, 1)),
        "verified image pair 4611686014132420610 refers to image id 2147483647, which the",
    ),
    "verified pair of a missing image": Case(
        _blob_edit(_FIRST_PAIR_ID, _pair_id(1, 99)), "refers to image id 99, which the database"
    ),
    "keypoints of 1 column": Case(  # x and y as 2 rows each: pycolmap read them as (n, 1)
        _blob_edit("UPDATE keypoints SET rows = rows * cols, cols = 1 WHERE image_id = 2"),
        "keypoints of image 2 (camera000001_frame000001.png) have 1 column, COLMAP writes 2, 4",
    ),
    "calibrate --model of another database": Case(
        _model_of_other_images,
        "6 of the model's 6 images are not in the database (e.g. other_camera000001_frame",
        argv=lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", w),
    ),
    "inlier matches of 1 column": Case(
        _blob_edit("UPDATE two_view_geometries SET rows = rows * cols, cols = 1"),
        "the inlier matches of image pair 2147483649 have 1 column, COLMAP writes 2",
    ),
    # ----- issue 23: calibrate MODEL_DIR (a model's tracks) and several inputs
    "empty folder: neither a database nor a model": Case(
        lambda f, _: f, "not a COLMAP model folder either (no cameras, images, points3D"
    ),
    "model folder with only cameras.bin": Case(
        _only_cameras_bin, "not a COLMAP model (no images, points3D .bin/.txt)"
    ),
    "model folder: truncated images.bin": Case(
        _models({"images": 3000}), "truncated COLMAP model file"
    ),
    "model folder: garbage points3D.bin": Case(_models({"points3D": None}), "points3D.bin"),
    "model of 2 registered images": Case(
        _two_image_model, "the reconstruction has 2 registered image(s), at least 3"
    ),
    "model folder with --write": Case(
        _models(), "--write stores the estimate in a database: ", ("--write",)
    ),
    "model folder with --model and --output": Case(
        _models(),
        "--model goes with a database: ",
        argv=lambda f, p, w: ("calibrate", p, "--model", p, "--output", w),
    ),
    "model folder, --json is a file of it": Case(
        _models(),
        "is a file of MODEL: refusing",
        argv=lambda f, p, w: ("calibrate", p, "--json", p / "cameras.bin"),
    ),
    "a glob pattern that matches nothing": Case(
        lambda f, _: f / "*.sqlite", "no database or model folder matches"
    ),
    "several databases with --model": Case(
        _model_and_database,
        "--model takes one database, not several inputs",
        argv=lambda f, p, w: ("calibrate", p, p, "--model", f / "sparse" / "0", "--output", w),
    ),
    "several inputs, --write with a model folder": Case(
        _model_and_database,
        "is a COLMAP model folder",
        argv=lambda f, p, w: ("calibrate", p, f / "sparse" / "0", "--write"),
    ),
    "several databases, --json is one of them": Case(
        _two_copies,
        "--json",
        argv=lambda f, p, w: ("calibrate", p, f / "other.db", "--json", f / "other.db"),
    ),
    "a glob of databases, --json is one of them": Case(
        _two_copies,
        "other.db is the database: refusing",
        argv=lambda f, p, w: ("calibrate", f / "*.db", "--json", f / "other.db"),
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input(
    name: str, good_database: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    case = CASES[name]
    folder = tmp_path / "data"
    folder.mkdir()
    path = case.make(folder, good_database)
    if case.read_only:
        path.chmod(0o444)
    before = tree(folder)
    workspace = tmp_path / "ws"
    if case.argv is None:
        args = ("calibrate", path, *case.args)
    else:  # "{path}" and "{folder}" in a row's arguments stand for the made path and folder
        args = tuple(
            str(a).format(path=path, folder=folder) if "{" in str(a) else a
            for a in case.argv(folder, path, workspace)
        )
    if case.unreadable is not None:
        (folder / case.unreadable).chmod(0)
    if case.preexec_fn is not None:
        result = run_cli(*args, preexec_fn=case.preexec_fn)
    elif case.lock is not None:
        statement, journal_mode = case.lock
        with holding_lock(path, statement, journal_mode):
            result = run_main(*args)
    else:
        result = run_main(*args)
    if case.unreadable is not None:
        (folder / case.unreadable).chmod(0o644)
    assert_one_error_line(result, case.fragment, case.status)
    assert tree(folder) == before  # every file byte-identical, none added or removed
    assert not workspace.exists()  # refused before the workspace was made
    # A results table only if computed: outputs (--json, then --write) come last, so a
    # failing one does not lose the estimate.
    assert result.stdout == "" or "--json" in args or "--write" in args


def test_jittered_copies_determine_nothing_and_write_nothing(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Three copies of one image with 1.5 px jitter pass the duplicate check (about 2.5 px
    apart) but have no parallax: every parameter is reported undetermined, the prior is
    returned, and ``--write`` leaves the database as it was (no backup either)."""
    path = _jittered_copies(tmp_path, tmp_path)
    before, files = sha256(path), listing(tmp_path)
    out = tmp_path / "result.json"
    result = run_main("calibrate", path, "--prior", PRIOR, "--write", "--json", out)
    assert result.returncode == 0, result.stderr
    (warning,) = result.stderr.strip().splitlines()
    assert warning.startswith("warning: camera 1: fx (") and "too similar images" in warning
    assert "camera 1 not written: the images determine none of its values" in result.stdout
    (entry,) = json.loads(out.read_text())
    assert not any(entry["observable"].values()) and not any(entry["estimated"].values())
    np.testing.assert_allclose([entry[k] for k in ("fx", "fy", "cx", "cy")], PRIOR_VALUES)
    assert sha256(path) == before and listing(tmp_path) == sorted([*files, "result.json"])


# --------------------------------------------------------------------------- Ctrl-C, in process


@pytest.fixture
def database_copy(good_database: Path, tmp_path: Path) -> Path:
    path = tmp_path / "database.db"
    shutil.copyfile(good_database, path)
    return path


def _after(function: Callable, action: Callable[[], None]) -> Callable:
    """``function`` followed by ``action`` (fault injection right after a step)."""

    def wrapped(*args: object, **kwargs: object) -> object:
        result = function(*args, **kwargs)
        action()
        return result

    return wrapped


def _before(function: Callable, action: Callable[[], None]) -> Callable:
    def wrapped(*args: object, **kwargs: object) -> object:
        action()
        return function(*args, **kwargs)

    return wrapped


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


#: Each terminating signal's disposition in an interactive terminal.
SIGNAL_DISPOSITIONS = {
    signal.SIGINT: signal.default_int_handler,
    signal.SIGTERM: signal.SIG_DFL,
    signal.SIGHUP: signal.SIG_DFL,
}

#: How each signal ends a run: its one line and exit status.
SIGNAL_ENDINGS = {
    "sigint": (_send_sigint, "error: interrupted", 130),
    "sigterm": (_send_sigterm, "error: terminated", 143),
    "sighup": (_send_sighup, "error: terminated (hangup)", 129),
}


def _main(run_main: Callable[..., CliResult], *args: object) -> tuple[int, list[str]]:
    """Exit status and stderr lines of the command line, in this process."""
    result = run_main(*args)
    return result.returncode, result.stderr.splitlines()


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
        _after(original, lambda: calls.append(1) or _raise_interrupt()),
    )
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
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
    wrap = _after if when == "after" else _before
    monkeypatch.setattr(database_module, function, wrap(getattr(database_module, function), action))
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
    assert (status, lines) == (expected_status, [line])
    assert sha256(database_copy) == before
    assert listing(database_copy.parent) == ["database.db"]


def test_interrupt_during_commit_is_held_until_written(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """A SIGINT arriving as COMMIT starts: the commit completes, the backup is kept, 130."""
    original_bytes = database_copy.read_bytes()
    monkeypatch.setattr(database_module, "_commit", _before(database_module._commit, _send_sigint))
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
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
    monkeypatch.setattr(database_module, "_commit", _before(database_module._commit, send))
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
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
    copy = database_module._copy_database

    def watched(path: Path, target: Path) -> None:
        seen.append(listing(path.parent))
        copy(path, target)
        seen.append(listing(path.parent))

    monkeypatch.setattr(database_module, "_copy_database", watched)
    status, _ = _main(run_main, "calibrate", database_copy, *QUICK)
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


def test_no_space_for_the_backup(
    database_copy: Path, monkeypatch: pytest.MonkeyPatch, run_main: Callable[..., CliResult]
) -> None:
    """The backup copy fails (ENOSPC): one line, nothing written, the partial .bak removed."""
    before = sha256(database_copy)

    def full_disk(path: Path, target: Path) -> None:
        target.write_bytes(path.read_bytes()[:4096])  # a partial copy, then the disk is full
        raise OSError(28, os.strerror(28), str(target))

    monkeypatch.setattr(database_module, "_copy_database", full_disk)
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
    assert status == 2
    assert lines == [
        f"error: cannot back up the database, nothing written: {database_copy} "
        "(No space left on device)"
    ]
    assert sha256(database_copy) == before
    assert listing(database_copy.parent) == ["database.db"]


#: In a child: write new params to the database argv[1] with the backup's copy replaced by
#: a partial copy, then argv[2]: "kill" (SIGKILL itself) or "wait" (hold the write lock
#: until stdin closes).
_HALF_A_BACKUP = """
import os, signal, sys
from pathlib import Path
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.database.writing import write_intrinsics

def partial_copy(path, target):
    target.write_bytes(path.read_bytes()[:4096])
    if sys.argv[2] == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    print("copying", flush=True)
    sys.stdin.readline()
    os._exit(0)

sys.modules[write_intrinsics.__module__]._copy_database = partial_copy
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
    status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
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
        status, lines = _main(run_main, "calibrate", database_copy, *QUICK)
        locked = f"error: database is locked by another process: {database_copy}"
        assert (status, lines) == (2, [locked])
        assert _temporary_copies(database_copy.parent) == [running]
    finally:
        assert child.stdin is not None
        child.stdin.close()
        child.wait(timeout=60)


# --------------------------------------------------------------------------- Ctrl-C, real SIGINT


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


# --------------------------------------------------------------------------- issue 15: outputs

QUICK_READ = ("--prior", PRIOR, "--max-triplets", "3", "--no-focal-search")


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


def test_repeated_camera_id_is_calibrated_once(
    database_copy: Path, tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """``--camera-id 1 --camera-id 1``: one result, not two (issue 15, item 8)."""
    out = tmp_path / "result.json"
    result = run_main(
        "calibrate",
        database_copy,
        *QUICK_READ,
        "--camera-id",
        "1",
        "--camera-id",
        "1",
        "--json",
        out,
    )
    assert result.returncode == 0, result.stderr
    assert [entry["camera_id"] for entry in json.loads(out.read_text())] == [1]
    rows = [line for line in result.stdout.splitlines()[1:] if line.split()[0].isdigit()]
    assert len(rows) == 1  # one camera (its std line follows it)


@pytest.mark.slow  # the whole run: calibration, mapping, bundle adjustment
def test_run_copies_what_is_still_in_the_wal(good_database: Path, tmp_path: Path) -> None:
    """``run --database`` copies with SQLite's backup API: committed rows still in the
    ``-wal`` reach the workspace's copy (a copy of the main file lost the verified
    matches, and mapping found none; issue 15, item 4). The input stays as it was."""
    source = tmp_path / "input" / "database.db"
    source.parent.mkdir()
    shutil.copyfile(good_database, source)
    con = sqlite3.connect(source, isolation_level=None)
    try:
        assert con.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
        rows = con.execute("SELECT * FROM two_view_geometries").fetchall()
        con.execute("DELETE FROM two_view_geometries")
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")  # the main file has no matches now
        con.execute("PRAGMA wal_autocheckpoint=0")
        marks = ",".join("?" * len(rows[0]))
        con.executemany(f"INSERT INTO two_view_geometries VALUES ({marks})", rows)
        wal = source.with_name("database.db-wal")
        assert wal.stat().st_size > 0  # committed, and only in the -wal while con is open
        before = sha256(source), sha256(wal)
        workspace = tmp_path / "ws"
        result = run_cli("run", tmp_path / "no-images", workspace, "--database", source)
        assert (sha256(source), sha256(wal)) == before
    finally:
        con.close()
    assert result.returncode == 0, result.stderr
    copy = sqlite3.connect(workspace / "database.db")
    try:
        assert copy.execute("SELECT COUNT(*) FROM two_view_geometries").fetchone() == (len(rows),)
    finally:
        copy.close()
    report = json.loads((workspace / "report.json").read_text())
    assert report["num_registered_images"] == 6


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
        batch_module, "calibrate_groups", _after(batch_module.calibrate_groups, overflow)
    )
    with caplog.at_level("INFO", logger="colmap_trifocal"):
        status, lines = _main(run_main, "calibrate", database_copy, *QUICK_READ)
    assert (status, lines) == (0, [])
    assert any("RuntimeWarning: overflow" in r.getMessage() for r in caplog.records)
