"""How the bad-input rows build their inputs: databases, models, image folders, commands.

Each builder is ``(folder, good database) -> path``: it makes the row's input inside
``folder`` (from a copy of the good database where it needs one) and returns the path the
command is given; ``argv`` helpers give a row's command line from ``(folder, path,
workspace)``.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from conftest import synthesize, texture_views

from bad_input.table import HEIGHT, PARAMS, WIDTH, Config


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


def copy_good(folder: Path, good: Path) -> Path:
    target = folder / "database.db"
    shutil.copyfile(good, target)
    return target


def text_file(folder: Path, _good: Path) -> Path:
    path = folder / "notes.db"
    path.write_text("these are my notes, not a database\n" * 20)
    return path


def empty_file(folder: Path, _good: Path) -> Path:
    path = folder / "empty.db"
    path.touch()
    return path


def truncated_sqlite(folder: Path, good: Path) -> Path:
    path = folder / "truncated.db"
    data = good.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def other_tool(folder: Path, _good: Path) -> Path:
    path = folder / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE photos (id INTEGER PRIMARY KEY, path TEXT)")
    con.execute("INSERT INTO photos (path) VALUES ('a.jpg'), ('b.jpg'), ('c.jpg')")
    con.commit()
    con.close()
    return path


def rollback_journal_copy(folder: Path, good: Path) -> Path:
    """A copy in rollback-journal mode, where an EXCLUSIVE lock also blocks readers."""
    path = copy_good(folder, good)
    con = sqlite3.connect(path)
    con.execute("PRAGMA journal_mode=DELETE")
    con.close()
    return path


def without_rows(*tables: str) -> Callable[[Path, Path], Path]:
    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
        con = sqlite3.connect(path)
        for table in tables:
            con.execute(f"DELETE FROM {table}")
        con.commit()
        con.close()
        return path

    return make


def empty_colmap(folder: Path, _good: Path) -> Path:
    path = folder / "new.db"
    pycolmap.Database.open(str(path)).close()
    return path


def all_degenerate(folder: Path, good: Path) -> Path:
    path = copy_good(folder, good)
    with pycolmap.Database.open(str(path)) as db:
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            geometry.config = Config.DEGENERATE
            db.update_two_view_geometry(*pycolmap.pair_id_to_image_pair(pair_id), geometry)
    return path


def random_keypoints(rng: np.random.Generator, count: int) -> np.ndarray:
    return rng.uniform([0, 0], [WIDTH, HEIGHT], size=(count, 2))


def random_consistent_matches(folder: Path, _good: Path) -> Path:
    """Matches of random points: 3-cycle consistent (so they form tracks), but no geometry."""
    rng = np.random.default_rng(7)
    tracks = 100
    keypoints = [random_keypoints(rng, tracks) for _ in range(3)]
    order = [rng.permutation(tracks) for _ in range(3)]  # track -> keypoint in each image
    matches = {(a, b): np.column_stack([order[a - 1], order[b - 1]]) for a, b in all_pairs(3)}
    path = folder / "outliers.db"
    write_database(path, keypoints, matches)
    return path


def random_inconsistent_matches(folder: Path, _good: Path) -> Path:
    """Random matches: hardly a keypoint matched in one pair is matched alike in the others."""
    rng = np.random.default_rng(8)
    count = 300
    keypoints = [random_keypoints(rng, count) for _ in range(4)]
    matches = {
        pair: np.column_stack([rng.permutation(count), rng.permutation(count)])
        for pair in all_pairs(4)
    }
    path = folder / "outliers.db"
    write_database(path, keypoints, matches)
    return path


def synthetic_database(
    frames: int = 6, model: str = "PINHOLE", params: list[float] | None = None, points: int = 400
):
    def make(folder: Path, _good: Path) -> Path:
        path = folder / "database.db"
        synthesize(path, model, params or PARAMS, frames=frames, points=points)
        return path

    return make


def identical_images(folder: Path, _good: Path) -> Path:
    """Three copies of one image: the keypoints coincide (zero baseline)."""
    rng = np.random.default_rng(9)
    xy = random_keypoints(rng, 400)
    identity = np.column_stack([np.arange(400), np.arange(400)])
    path = folder / "copies.db"
    write_database(path, [xy, xy, xy], {pair: identity for pair in all_pairs(3)})
    return path


def jittered_copies(folder: Path, _good: Path) -> Path:
    """Three copies of one image with 1.5 px of keypoint jitter: no parallax at all."""
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [WIDTH, HEIGHT], size=(300, 2))
    copies = [xy + rng.normal(0.0, 1.5, xy.shape) for _ in range(3)]
    identity = np.column_stack([np.arange(300), np.arange(300)])
    path = folder / "copies.db"
    write_database(path, copies, {pair: identity for pair in all_pairs(3)})
    return path


def fisheye(folder: Path, _good: Path) -> Path:
    path = folder / "fisheye.db"
    synthesize(path, "OPENCV_FISHEYE", [*PARAMS, 0.01, 0.0, 0.0, 0.0])
    return path


def blob_edit(sql: str, *values: object) -> Callable[[Path, Path], Path]:
    """A copy of the good database with one UPDATE applied (sqlite3, no pycolmap)."""

    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
        con = sqlite3.connect(path)
        con.execute(sql, values)
        con.commit()
        con.close()
        return path

    return make


def keypoint_value(value: float) -> Callable[[Path, Path], Path]:
    """Keypoint 5 of image 1 gets ``value`` as its x coordinate."""

    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
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


def stored_params(*values: float) -> Callable[[Path, Path], Path]:
    return blob_edit("UPDATE cameras SET params = ?", np.array(values, "<f8").tobytes())


def link_to_database(kind: str) -> Callable[[Path, Path], Path]:
    """A copy of the good database and ``out.json``, a symlink or a hard link to it."""

    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
        (os.symlink if kind == "symlink" else os.link)(path, folder / "out.json")
        return path

    return make


def hot_journal(folder: Path, good: Path) -> Path:
    """A database whose writer was killed mid-transaction: a hot ``-journal`` next to it."""
    path = rollback_journal_copy(folder, good)
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
FIRST_PAIR_ID = f"UPDATE two_view_geometries SET pair_id = ? WHERE pair_id = {MAX_NUM_IMAGES + 2}"


def colmap_pair_id(id1: int, id2: int) -> int:
    return MAX_NUM_IMAGES * id1 + id2


MODEL_BYTES: dict[str, bytes] = {}


def make_model(folder: Path, cut: dict[str, int | None] | None = None, images: bool = True) -> Path:
    """A pycolmap synthetic model in ``folder/sparse/0`` (and ``folder/images`` if asked);
    ``cut[name] = n`` keeps the first n bytes of ``name.bin`` (None: random bytes)."""
    if not MODEL_BYTES:
        with tempfile.TemporaryDirectory() as tmp:
            reconstruction = synthesize(Path(tmp) / "model.db", "PINHOLE", PARAMS)
            reconstruction.write(tmp)
            MODEL_BYTES.update({p.name: p.read_bytes() for p in Path(tmp).glob("*.bin")})
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    if images:
        (folder / "images").mkdir()
    rng = np.random.default_rng(3)
    for name, data in MODEL_BYTES.items():
        size = (cut or {}).get(name.removesuffix(".bin"), len(data))
        data = rng.bytes(5000) if size is None else data[:size]
        (model / name).write_bytes(data)
    return model


def models_with(cut: dict[str, int | None] | None = None, images: bool = True):
    return lambda folder, _good: make_model(folder, cut, images)


def run_database(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``run IMAGES WORKSPACE --database PATH ARGS`` (the folder as IMAGES)."""
    return lambda folder, path, workspace: ("run", folder, workspace, "--database", path, *args)


def model_of_other_images(folder: Path, good: Path) -> Path:
    """The good database, and in ``folder/sparse/0`` a model of the same camera and image
    size whose images have other names (another database's)."""
    model = make_model(folder, images=False)
    reconstruction = pycolmap.Reconstruction(model)
    for image in reconstruction.images.values():
        image.name = f"other_{image.name}"
    reconstruction.write(model)
    return copy_good(folder, good)


def database_in_workspace(folder: Path, good: Path) -> Path:
    """An earlier run's workspace (the folder) with a model in sparse/0; the database in
    another folder of it."""
    make_model(folder, images=False)
    (folder / "input").mkdir()
    return copy_good(folder / "input", good)


def three_images(folder: Path, names: tuple[str, ...] = ("a.png", "b.png", "c.png")) -> Path:
    """``folder`` with three small readable images (random grey levels, 64 x 48 pixels)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(11)
    for name in names:
        assert cv2.imwrite(str(folder / name), rng.integers(0, 256, (48, 64), np.uint8))
    return folder


def images_and_link_to_them(folder: Path, _good: Path) -> Path:
    """An image folder ``photos`` and a symlink ``link`` to it."""
    images = three_images(folder / "photos")
    (folder / "link").symlink_to(images)
    return images


def colmap_project(folder: Path, good: Path) -> Path:
    """A COLMAP project: ``project/images`` and the user's own ``project/database.db``."""
    three_images(folder / "project" / "images")
    shutil.copyfile(good, folder / "project" / "database.db")
    return folder / "project"


def two_databases(folder: Path, good: Path) -> Path:
    """``a/database.db`` and ``b/database.db``, copies of the good database."""
    for name in ("a", "b"):
        (folder / name).mkdir()
        shutil.copyfile(good, folder / name / "database.db")
    return folder / "a" / "database.db"


def database_and_backup(folder: Path, good: Path) -> Path:
    """The good database and an earlier write's backup ``database.db.bak1``."""
    shutil.copyfile(good, folder / "database.db.bak1")
    return copy_good(folder, good)


def earlier_demo(folder: Path, good: Path) -> Path:
    """A folder where an earlier ``demo --keep`` left ``demo.db`` (here: another database)."""
    shutil.copyfile(good, folder / "demo.db")
    return folder / "demo.db"


def earlier_demo_workspace(folder: Path, good: Path) -> Path:
    """A folder where an earlier ``demo --keep`` left its workspace ``demo/``."""
    (folder / "demo").mkdir()
    shutil.copyfile(good, folder / "demo" / "database.db")
    return folder / "demo" / "database.db"


def images_in_sparse(folder: Path, _good: Path) -> Path:
    """An earlier run's workspace (the folder) whose ``sparse/`` also holds the images."""
    return three_images(folder / "sparse")


def images_linked_into_sparse(folder: Path, _good: Path) -> Path:
    """An image folder whose images are symlinks to files in the ``sparse/`` of an earlier
    run's workspace ``ws``."""
    three_images(folder / "ws" / "sparse")
    (folder / "photos").mkdir()
    for name in ("a.png", "b.png", "c.png"):
        (folder / "photos" / name).symlink_to(folder / "ws" / "sparse" / name)
    return folder / "photos"


def link_to_images_in_sparse(folder: Path, good: Path) -> Path:
    """``folder/photos``, a symlink to the workspace's ``sparse/`` that holds the images."""
    images_in_sparse(folder, good)
    (folder / "photos").symlink_to(folder / "sparse")
    return folder / "photos"


def images_and_hard_link(folder: Path, _good: Path) -> Path:
    """``folder/photos`` with three images, ``folder/out.png`` a hard link to one of them."""
    photos = three_images(folder / "photos")
    os.link(photos / "a.png", folder / "out.png")
    return photos


def with_companion(suffix: str) -> Callable[[Path, Path], Path]:
    """A copy of the good database with a companion file (``-shm``, ``-wal``) beside it."""

    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
        path.with_name(path.name + suffix).write_bytes(b"\0" * 32768)
        return path

    return make


def encoded(suffix: str, image: np.ndarray, *params: int) -> bytes:
    ok, data = cv2.imencode(suffix, image, list(params))
    assert ok
    return data.tobytes()


def image_folder(add: Callable[[Path], object], good: int = 2) -> Callable[[Path, Path], Path]:
    """An image folder ``folder/images``: ``good`` JPEGs, then ``add(images)`` puts the bad
    file(s) in."""

    def make(folder: Path, _good: Path) -> Path:
        images = folder / "images"
        images.mkdir()
        for index, image in enumerate(texture_views(good)):
            (images / f"{index:02d}.jpg").write_bytes(encoded(".jpg", image))
        add(images)
        return images

    return make


def model_and_database(folder: Path, good: Path) -> Path:
    """A model in ``folder/sparse/0`` and the database at ``folder/database.db``."""
    return copy_good(make_model(folder).parent.parent, good)


def model_database_and_link(folder: Path, good: Path) -> Path:
    """As :func:`model_and_database`, with ``folder/out.json`` a symlink to a model file."""
    path = model_and_database(folder, good)
    (folder / "out.json").symlink_to(folder / "sparse" / "0" / "images.bin")
    return path


def model_database_and_empty_output(folder: Path, good: Path) -> Path:
    """As :func:`model_and_database`, with an empty folder ``folder/out``."""
    path = model_and_database(folder, good)
    (folder / "out").mkdir()
    return path


def calibrate_model(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``calibrate PATH --model FOLDER/sparse/0 --output WORKSPACE ARGS``."""
    return lambda f, p, w: ("calibrate", p, "--model", f / "sparse" / "0", "--output", w, *args)


def notes_file(folder: Path, _good: Path) -> Path:
    path = folder / "notes.txt"
    path.write_text("mine\n")
    return path


def write_file(name: str, data: bytes) -> Callable[[Path], object]:
    return lambda images: (images / name).write_bytes(data)


def cut_file(name: str, data: bytes, keep: float = 0.5) -> Callable[[Path], object]:
    """``name`` holding the first ``keep`` share of ``data`` (a truncated download)."""
    return write_file(name, data[: int(len(data) * keep)])


def unix_socket(images: Path) -> None:
    import socket

    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(images / "x.png"))  # the socket file stays after the close


def run_image_folder(*args: object) -> Callable[[Path, Path, Path], tuple]:
    """``run IMAGES WORKSPACE ARGS`` on the made image folder."""
    return lambda folder, path, workspace: ("run", path, workspace, *args)


def unwritable_workspace(folder: Path, good: Path) -> Path:
    """Three good images and an existing, empty workspace ``folder/ws`` without write
    permission (chmod 555)."""
    images = image_folder(lambda _: None, good=3)(folder, good)
    (folder / "ws").mkdir(mode=0o555)
    (folder / "ws").chmod(0o555)
    return images


JPEG = encoded(".jpg", texture_views(1)[0])


PROGRESSIVE_JPEG = encoded(".jpg", texture_views(1)[0], cv2.IMWRITE_JPEG_PROGRESSIVE, 1)


PNG16 = encoded(".png", texture_views(1)[0].astype(np.uint16) * 257)


def only_cameras_bin(folder: Path, _good: Path) -> Path:
    """A model folder holding only ``cameras.bin``."""
    model = make_model(folder)
    for name in ("images.bin", "points3D.bin"):
        (model / name).unlink()
    return model


def two_image_model(folder: Path, _good: Path) -> Path:
    """A model of 2 registered images (their tracks give no triplet)."""
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    with tempfile.TemporaryDirectory() as tmp:
        synthesize(Path(tmp) / "model.db", "PINHOLE", PARAMS, frames=2).write(model)
    return model


def two_copies(folder: Path, good: Path) -> Path:
    """``folder/database.db`` and ``folder/other.db``: two copies of the good database."""
    shutil.copyfile(good, folder / "other.db")
    return copy_good(folder, good)


def stored_radial(k1: float) -> Callable[[Path, Path], Path]:
    """A copy of the good database whose camera is SIMPLE_RADIAL with distortion ``k1``."""
    fx, _, cx, cy = PARAMS
    params = np.array([fx, cx, cy, k1], "<f8").tobytes()
    return blob_edit("UPDATE cameras SET model = 2, params = ?", params)


def user_table(sql: str) -> Callable[[Path, Path], Path]:
    """A copy of the good database with the user's own SQL applied: a table of theirs."""

    def make(folder: Path, good: Path) -> Path:
        path = copy_good(folder, good)
        con = sqlite3.connect(path)
        con.executescript(sql)
        con.commit()
        con.close()
        return path

    return make


def utf16_copy(folder: Path, good: Path) -> Path:
    """The good database dumped into a new one with UTF-16 text (``PRAGMA encoding``)."""
    path = folder / "database.db"
    source, target = sqlite3.connect(good), sqlite3.connect(path)
    target.execute("PRAGMA encoding = 'UTF-16le'")
    for statement in source.iterdump():
        if not statement.startswith(("BEGIN", "COMMIT")):
            target.execute(statement)
    target.commit()
    assert target.execute("PRAGMA encoding").fetchone() == ("UTF-16le",)
    source.close()
    target.close()
    return path


#: A sparse file's size: far more than memory, nothing on disk.
SPARSE_BYTES = 60 << 30


def sparse_model_file(name: str) -> Callable[[Path, Path], Path]:
    """A model whose file ``name`` keeps its records and is then extended, sparse, to
    :data:`SPARSE_BYTES` (zeros that take no disk space)."""

    def make(folder: Path, _good: Path) -> Path:
        model = make_model(folder)
        os.truncate(model / name, SPARSE_BYTES)
        return model

    return make


def special_model_file(name: str) -> Callable[[Path, Path], Path]:
    """A model whose file ``name`` is a FIFO (no writer ever comes)."""

    def make(folder: Path, _good: Path) -> Path:
        model = make_model(folder)
        (model / name).unlink()
        os.mkfifo(model / name)
        return model

    return make


def edited_model(edit: Callable[[pycolmap.Reconstruction], object]) -> Callable[[Path, Path], Path]:
    """A model read back, changed by ``edit`` and written again (pycolmap writes what it
    is given: NaN params, a pose at 1e300)."""

    def make(folder: Path, _good: Path) -> Path:
        model = make_model(folder)
        reconstruction = pycolmap.Reconstruction(model)
        edit(reconstruction)
        reconstruction.write(model)
        return model

    return make


def nan_camera(reconstruction: pycolmap.Reconstruction) -> None:
    for camera in reconstruction.cameras.values():
        camera.params = np.array([np.nan, *PARAMS[1:]])


def far_pose(reconstruction: pycolmap.Reconstruction) -> None:
    image = reconstruction.image(min(reconstruction.reg_image_ids()))
    pose = image.cam_from_world()
    image.frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, np.array([1e300, 0.0, 0.0]))


def far_points(reconstruction: pycolmap.Reconstruction) -> None:
    for point in reconstruction.points3D.values():
        point.xyz = np.array([1e300, -1e300, 1e300])


def show_png(folder: Path, path: Path, workspace: Path) -> tuple:
    """``show PATH --png`` into the folder above the row's (so the row's files stay as
    they were)."""
    return ("show", path, "--png", folder.parent / "view.png")


def good_and_fifo(folder: Path, good: Path) -> Path:
    """A copy of the good database and ``folder/out``, a FIFO nobody reads."""
    os.mkfifo(folder / "out")
    return copy_good(folder, good)


def model_and_fifo(folder: Path, _good: Path) -> Path:
    """A model in ``folder/sparse/0`` and ``folder/out``, a FIFO nobody reads."""
    os.mkfifo(folder / "out")
    return make_model(folder)


def good_and_socket(folder: Path, good: Path) -> Path:
    """A copy of the good database and ``folder/out``, a UNIX socket."""
    import socket

    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(folder / "out"))
    return copy_good(folder, good)
