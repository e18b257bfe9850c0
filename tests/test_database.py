"""Tests of colmap_trifocal.database.snapshot on databases made by pycolmap.synthesize_dataset."""

from __future__ import annotations

import hashlib
import os
import shutil
import sqlite3
import subprocess
import sys
from contextlib import closing
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_trifocal.common.errors import CalibrationError
from colmap_trifocal.database import sqlite_files as database_module
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.database.writing import write_intrinsics

SIMPLE_RADIAL_PARAMS = [1280.0, 512.0, 384.0, 0.05]
PINHOLE_PARAMS = [1100.0, 1250.0, 530.0, 370.0]
Config = pycolmap.TwoViewGeometryConfiguration


def _synthesize(path: Path, **options: object) -> pycolmap.Reconstruction:
    """Write a synthetic COLMAP database to ``path``; return the ground truth."""
    settings: dict[str, object] = {
        "num_rigs": 1,
        "num_cameras_per_rig": 1,
        "num_frames_per_rig": 5,
        "num_points3D": 300,
    }
    settings.update(options)
    pycolmap.set_random_seed(0)  # the scene must not depend on the tests run before
    with pycolmap.Database.open(str(path)) as db:
        return pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(**settings), db)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _copy(src: Path, directory: Path, name: str = "database.db") -> Path:
    dst = directory / name
    shutil.copy2(src, dst)
    return dst


def _sampson(fundamental: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance (pixels) of correspondences x1 <-> x2 to x2^T F x1 = 0."""
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    fx1 = h1 @ fundamental.T
    ftx2 = h2 @ fundamental
    residual = np.sum(h2 * fx1, axis=1)
    norm = np.sqrt(fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2)
    return np.abs(residual) / norm


def _database_rows(path: Path) -> dict[str, list[tuple]]:
    """All rows of all tables (read without creating companion files)."""
    con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro&immutable=1", uri=True)
    try:
        tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        return {t: sorted(con.execute(f"SELECT * FROM {t}").fetchall()) for t in tables}
    finally:
        con.close()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pycolmap.Reconstruction]:
    """5 images, 1 SIMPLE_RADIAL camera (k = 0.05), 300 points, exhaustive matches."""
    path = tmp_path_factory.mktemp("synthetic") / "database.db"
    return path, _synthesize(path)


@pytest.fixture(scope="module")
def synthetic_db(synthetic: tuple[Path, pycolmap.Reconstruction]) -> Path:
    return synthetic[0]


@pytest.fixture(scope="module")
def pinhole_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rig of 2 PINHOLE cameras (fx != fy) x 3 frames = 6 images."""
    path = tmp_path_factory.mktemp("pinhole") / "database.db"
    _synthesize(
        path,
        num_cameras_per_rig=2,
        num_frames_per_rig=3,
        num_points3D=200,
        camera_model_id=pycolmap.CameraModelId.PINHOLE,
        camera_params=PINHOLE_PARAMS,
    )
    return path


# --------------------------------------------------------------------------- reading


def test_contents(synthetic: tuple[Path, pycolmap.Reconstruction]) -> None:
    path, truth = synthetic
    contents = read_database(path, fundamentals=True)

    assert len(contents.image_names) == 5
    assert set(contents.image_names) == set(contents.image_camera) == set(contents.keypoints)
    assert list(contents.cameras) == [1]
    camera = contents.cameras[1]
    assert camera.model == "SIMPLE_RADIAL"
    assert (camera.width, camera.height) == (1024, 768)
    np.testing.assert_array_equal(camera.params, SIMPLE_RADIAL_PARAMS)
    assert set(contents.image_camera.values()) == {1}

    for image_id, xy in contents.keypoints.items():
        image = truth.images[image_id]
        assert contents.image_names[image_id] == image.name
        assert xy.dtype == np.float64 and xy.ndim == 2 and xy.shape[1] == 2
        assert xy.shape[0] == len(image.points2D) == 310  # 300 tracked + 10 unmatched
        truth_xy = np.array([p.xy for p in image.points2D])
        np.testing.assert_allclose(xy, truth_xy, atol=1e-3)  # stored as float32

    assert len(contents.matches) == 10  # exhaustive over 5 images
    assert set(contents.fundamentals) == set(contents.matches)
    for (id1, id2), matches in contents.matches.items():
        assert id1 < id2
        assert matches.dtype == np.int32 and matches.shape == (300, 2)
        assert matches.min() >= 0
        assert matches[:, 0].max() < len(contents.keypoints[id1])
        assert matches[:, 1].max() < len(contents.keypoints[id2])
        # Column 0 indexes image id1, column 1 image id2: both see the same 3D point.
        points1 = truth.images[id1].points2D
        points2 = truth.images[id2].points2D
        track1 = [points1[int(i)].point3D_id for i in matches[:, 0]]
        track2 = [points2[int(i)].point3D_id for i in matches[:, 1]]
        assert track1 == track2
        assert contents.fundamentals[(id1, id2)].shape == (3, 3)


@pytest.mark.parametrize("fixture", ["synthetic_db", "pinhole_db"])
def test_fundamental_convention(fixture: str, request: pytest.FixtureRequest) -> None:
    """x2^T F x1 = 0 with x1 in image id1 (matches[:, 0]) and x2 in image id2."""
    contents = read_database(request.getfixturevalue(fixture), fundamentals=True)
    assert contents.fundamentals
    for (id1, id2), fundamental in contents.fundamentals.items():
        matches = contents.matches[(id1, id2)]
        x1 = contents.keypoints[id1][matches[:, 0]]
        x2 = contents.keypoints[id2][matches[:, 1]]
        error = np.median(_sampson(fundamental, x1, x2))
        assert error < 1.0, (id1, id2, error)
        # The other orientation is clearly wrong, so the check above is meaningful.
        assert np.median(_sampson(fundamental, x2, x1)) > 10 * max(error, 0.1)
        if fixture == "pinhole_db":  # no distortion: F is exact for raw keypoints
            assert error < 1e-3


@pytest.mark.parametrize("name", ["database.db", "my data #1?.db"])
def test_read_leaves_file_untouched(synthetic_db: Path, tmp_path: Path, name: str) -> None:
    path = _copy(synthetic_db, tmp_path, name)
    before = _sha256(path)
    mtime = path.stat().st_mtime_ns
    read_database(path)
    read_database(path)
    assert _sha256(path) == before
    assert path.stat().st_mtime_ns == mtime
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no -wal/-shm left behind


def test_read_read_only_file(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    before = _sha256(path)
    os.chmod(path, 0o444)
    try:
        assert len(read_database(path).image_names) == 5
    finally:
        os.chmod(path, 0o644)
    assert _sha256(path) == before


def test_read_sees_committed_changes_in_wal(synthetic_db: Path, tmp_path: Path) -> None:
    """Another process has the database open with committed changes still in its WAL."""
    path = _copy(synthetic_db, tmp_path)
    new_params = np.array([1300.0, 500.0, 380.0, 0.04])
    other = sqlite3.connect(path)
    try:
        other.execute("UPDATE cameras SET params = ? WHERE camera_id = 1", (new_params.tobytes(),))
        other.commit()
        assert (tmp_path / "database.db-wal").stat().st_size > 0
        main_file = _sha256(path)
        contents = read_database(path)
        np.testing.assert_array_equal(contents.cameras[1].params, new_params)
        assert _sha256(path) == main_file
    finally:
        other.close()


def test_pair_stored_in_the_other_order(synthetic_db: Path, tmp_path: Path) -> None:
    """A geometry written for (2, 1) is read back for (1, 2) with the same convention."""
    path = _copy(synthetic_db, tmp_path)
    original = read_database(path, fundamentals=True)
    with pycolmap.Database.open(str(path)) as db:
        geometry = db.read_two_view_geometry(1, 2)
        db.delete_two_view_geometry(1, 2)
        geometry.invert()  # now maps image 2 to image 1
        db.write_two_view_geometry(2, 1, geometry)
    contents = read_database(path, fundamentals=True)
    np.testing.assert_array_equal(contents.matches[(1, 2)], original.matches[(1, 2)])
    f_new = contents.fundamentals[(1, 2)]
    f_old = original.fundamentals[(1, 2)]
    np.testing.assert_allclose(
        f_new / np.linalg.norm(f_new), f_old / np.linalg.norm(f_old), atol=1e-9
    )


def test_fundamental_from_essential(pinhole_db: Path, tmp_path: Path) -> None:
    """CALIBRATED geometries without F: F = K2^-T E K1^-1 with each image's own camera."""
    path = _copy(pinhole_db, tmp_path)
    # Give camera 2 a different K and move its keypoints accordingly (E is unchanged).
    new_k2 = np.array([[900.0, 0.0, 500.0], [0.0, 950.0, 400.0], [0.0, 0.0, 1.0]])
    old_k = np.array([[1100.0, 0.0, 530.0], [0.0, 1250.0, 370.0], [0.0, 0.0, 1.0]])
    affine = (new_k2 @ np.linalg.inv(old_k))[:2]
    with pycolmap.Database.open(str(path)) as db:
        camera = db.read_camera(2)
        camera.params = [900.0, 950.0, 500.0, 400.0]
        db.update_camera(camera)
        for image in db.read_all_images():
            if image.camera_id == 2:
                keypoints = db.read_keypoints(image.image_id).astype(np.float64)
                xy1 = np.column_stack([keypoints[:, :2], np.ones(len(keypoints))])
                keypoints[:, :2] = xy1 @ affine.T
                db.update_keypoints(image.image_id, keypoints.astype(np.float32))
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            geometry.F = None
            geometry.config = Config.CALIBRATED
            db.update_two_view_geometry(*pycolmap.pair_id_to_image_pair(pair_id), geometry)

    contents = read_database(path, fundamentals=True)
    assert set(contents.fundamentals) == set(contents.matches)
    cameras_seen = set()
    for (id1, id2), fundamental in contents.fundamentals.items():
        cameras_seen.add((contents.image_camera[id1], contents.image_camera[id2]))
        matches = contents.matches[(id1, id2)]
        x1 = contents.keypoints[id1][matches[:, 0]]
        x2 = contents.keypoints[id2][matches[:, 1]]
        assert np.median(_sampson(fundamental, x1, x2)) < 1e-3
    assert {(1, 2), (2, 1)} <= cameras_seen  # both orders of distinct cameras exercised


def test_pairs_without_usable_f_and_watermarks(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    with pycolmap.Database.open(str(path)) as db:
        planar = db.read_two_view_geometry(1, 2)
        planar.F = None
        planar.E = None
        planar.config = Config.PLANAR
        db.update_two_view_geometry(1, 2, planar)
        watermark = db.read_two_view_geometry(1, 3)
        watermark.config = Config.WATERMARK
        db.update_two_view_geometry(1, 3, watermark)
        db.delete_two_view_geometry(2, 3)
    contents = read_database(path, fundamentals=True)
    assert (1, 2) in contents.matches and (1, 2) not in contents.fundamentals
    assert (1, 3) not in contents.matches
    assert (2, 3) not in contents.matches
    assert len(contents.matches) == 8 and len(contents.fundamentals) == 7


# --------------------------------------------------------------------------- read errors


def _error_message(path: Path) -> str:
    with pytest.raises(CalibrationError) as info:
        read_database(path)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_missing_path(tmp_path: Path) -> None:
    path = tmp_path / "missing.db"
    assert _error_message(path) == f"database not found: {path}"
    assert not path.exists()  # not created


def test_directory(tmp_path: Path) -> None:
    assert "is a directory" in _error_message(tmp_path)


@pytest.mark.parametrize("content", [b"", b"hello, this is not a database\n" * 10])
def test_not_sqlite(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "x.db"
    path.write_bytes(content)
    assert _error_message(path) == f"not an SQLite database: {path}"
    assert path.read_bytes() == content


def test_sqlite_without_colmap_tables(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE cameras (camera_id INTEGER)")
    con.commit()
    con.close()
    before = _sha256(path)
    message = _error_message(path)
    assert message.startswith("not a COLMAP database (no table images, keypoints,")
    assert _sha256(path) == before


def test_truncated(synthetic_db: Path, tmp_path: Path) -> None:
    path = tmp_path / "truncated.db"
    path.write_bytes(synthetic_db.read_bytes()[:40960])
    message = _error_message(path)
    assert "truncated or corrupt" in message or "not a COLMAP database" in message


def test_no_images(tmp_path: Path) -> None:
    path = tmp_path / "empty.db"
    pycolmap.Database.open(str(path)).close()  # an empty COLMAP database
    assert _error_message(path) == f"database has no images: {path}"


def test_fewer_than_three_images(tmp_path: Path) -> None:
    path = tmp_path / "two.db"
    _synthesize(path, num_frames_per_rig=2, num_points3D=50)
    assert "only 2 images, at least 3 are needed" in _error_message(path)


def test_no_verified_matches(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    with pycolmap.Database.open(str(path)) as db:
        db.clear_two_view_geometries()
    assert "no verified matches" in _error_message(path)


def test_locked_database(synthetic_db: Path, tmp_path: Path, monkeypatch) -> None:
    """A rollback-journal database exclusively locked by another connection."""
    path = _copy(synthetic_db, tmp_path)
    cameras = read_database(path).cameras
    con = sqlite3.connect(path, isolation_level=None)
    con.execute("PRAGMA journal_mode=DELETE")
    con.execute("BEGIN EXCLUSIVE")
    monkeypatch.setattr(database_module, "_LOCK_TIMEOUT_S", 0.05)
    try:
        assert _error_message(path) == f"database is locked by another process: {path}"
        with pytest.raises(CalibrationError, match="locked by another process"):
            write_intrinsics(path, cameras)
    finally:
        con.execute("ROLLBACK")
        con.close()


# --------------------------------------------------------------------------- writing


#: SIMPLE_RADIAL params after with_intrinsics(1234.5, 1236.5, 500.25, 390.75): f = mean.
WRITTEN_PARAMS = [1235.5, 500.25, 390.75, 0.05]


def _new_cameras(path: Path) -> dict[int, CameraInfo]:
    cameras = read_database(path).cameras
    return {
        cid: cam.with_intrinsics(1234.5, 1236.5, 500.25, 390.75) for cid, cam in cameras.items()
    }


def test_write_intrinsics(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    original_hash = _sha256(path)
    original_rows = _database_rows(path)
    new = _new_cameras(path)

    backup = write_intrinsics(path, new)

    assert backup == tmp_path / "database.db.bak"
    assert _database_rows(backup) == original_rows  # SQLite's backup: the rows, not the bytes
    assert original_hash != _sha256(path)
    np.testing.assert_array_equal(read_database(path).cameras[1].params, WRITTEN_PARAMS)
    rows = _database_rows(path)
    assert rows.keys() == original_rows.keys()
    for table, database_rows in rows.items():
        if table != "cameras":
            assert database_rows == original_rows[table], table
    (camera_row,) = rows["cameras"]
    (original_camera_row,) = original_rows["cameras"]
    params_column = 4  # camera_id, model, width, height, params, prior_focal_length
    assert camera_row[:params_column] == original_camera_row[:params_column]
    assert camera_row[params_column + 1 :] == original_camera_row[params_column + 1 :]
    assert np.frombuffer(camera_row[params_column], "<f8").tolist() == WRITTEN_PARAMS
    assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db", "database.db.bak"]


def test_second_write_keeps_first_backup(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    original_rows = _database_rows(path)
    first = write_intrinsics(path, _new_cameras(path))
    after_first = _database_rows(path)
    cameras = read_database(path).cameras
    second = write_intrinsics(path, {1: cameras[1].with_intrinsics(1000, 1000, 512, 384)})
    assert first == tmp_path / "database.db.bak"
    assert second == tmp_path / "database.db.bak1"
    assert _database_rows(first) == original_rows
    assert _database_rows(second) == after_first
    np.testing.assert_array_equal(read_database(path).cameras[1].params, [1000, 512, 384, 0.05])


def test_write_without_backup(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    assert write_intrinsics(path, _new_cameras(path), backup=False) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db"]


def test_write_backup_includes_wal(synthetic_db: Path, tmp_path: Path) -> None:
    """Committed changes still in another connection's WAL are in the backup."""
    path = _copy(synthetic_db, tmp_path)
    other = sqlite3.connect(path)
    try:
        other.execute("UPDATE images SET name = 'renamed.png' WHERE image_id = 1")
        other.commit()
        assert (tmp_path / "database.db-wal").stat().st_size > 0
        backup = write_intrinsics(path, _new_cameras(path))
    finally:
        other.close()
    backup_rows = _database_rows(backup)
    assert "renamed.png" in {row[1] for row in backup_rows["images"]}
    np.testing.assert_array_equal(
        np.frombuffer(backup_rows["cameras"][0][4], "<f8"), SIMPLE_RADIAL_PARAMS
    )
    assert read_database(path).image_names[1] == "renamed.png"


#: Another process that opens and closes the database in a loop, as a COLMAP GUI or a
#: script does: {database} and {statement} are filled in.
_OTHER_PROCESS = """
import sqlite3, sys, time
sys.stdout.write("ready\\n"); sys.stdout.flush()
while True:
    try:
        con = sqlite3.connect({database!r}, timeout=5)
        con.execute({statement!r}).fetchall()
        con.close()
    except sqlite3.OperationalError:
        pass
    time.sleep(0.001)
"""


def _stored_params(path: Path) -> list[float]:
    with closing(sqlite3.connect(path)) as fresh:
        (blob,) = fresh.execute("SELECT params FROM cameras WHERE camera_id = 1").fetchone()
    return np.frombuffer(blob, "<f8").tolist()


@pytest.mark.parametrize("statement", ["SELECT count(*) FROM images", "VACUUM"])
def test_write_survives_another_process_opening_the_database(
    synthetic_db: Path, tmp_path: Path, statement: str
) -> None:
    """A write that reports success is on disk while another process opens and closes the
    WAL database in a loop. Python's own copy of the file for the backup used to drop the
    write's POSIX locks (closing any descriptor of a file drops them all), so the other
    process's close checkpointed and deleted the -wal the write then committed into: 17
    of 20 writes were lost.

    A ``VACUUM`` loop can hold the lock past the write's wait; the write then refuses
    ("locked by another process") and must leave the parameters as they were. At least
    10 writes must report success, each then on disk."""
    path = _copy(synthetic_db, tmp_path)
    with sqlite3.connect(path) as con:
        assert con.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
    con.close()
    other = subprocess.Popen(
        [sys.executable, "-c", _OTHER_PROCESS.format(database=str(path), statement=statement)],
        stdout=subprocess.PIPE,
        text=True,
    )
    written, refused = 0, 0
    try:
        assert other.stdout is not None and other.stdout.readline() == "ready\n"
        while written < 10 and refused < 30:
            camera = read_database(path).cameras[1]
            before = camera.params.tolist()
            new = camera.with_intrinsics(*(camera.intrinsics * (1.0 + 0.001 * (written + 1))))
            try:
                backup = write_intrinsics(path, {1: new})
            except CalibrationError as exc:
                assert str(exc) == f"database is locked by another process: {path}"
                assert _stored_params(path) == before, "a refused write changed the database"
                refused += 1
                continue
            assert backup is not None and backup.is_file()
            backup.unlink()
            assert _stored_params(path) == new.params.tolist(), f"write {written} lost"
            written += 1
    finally:
        other.kill()
        other.wait()
    assert written == 10, f"{refused} of {written + refused} writes refused as locked"


def test_write_read_only_refused(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    new = _new_cameras(path)
    before = _sha256(path)
    os.chmod(path, 0o444)
    try:
        with pytest.raises(CalibrationError) as info:
            write_intrinsics(path, new)
        assert str(info.value) == f"cannot write to read-only database: {path}"
        assert _sha256(path) == before
        assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db"]
    finally:
        os.chmod(path, 0o644)


def test_write_rejects_mismatched_camera(synthetic_db: Path, tmp_path: Path) -> None:
    path = _copy(synthetic_db, tmp_path)
    before = _sha256(path)
    other_model = CameraInfo(1, "PINHOLE", 1024, 768, np.array([1000.0, 1000.0, 512.0, 384.0]))
    with pytest.raises(CalibrationError, match="differs in model or size"):
        write_intrinsics(path, {1: other_model})
    unknown = CameraInfo(7, "SIMPLE_RADIAL", 1024, 768, np.array(SIMPLE_RADIAL_PARAMS))
    with pytest.raises(CalibrationError, match="camera 7 is not in the database"):
        write_intrinsics(path, {7: unknown})
    assert _sha256(path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["database.db"]


def test_write_errors_for_bad_paths(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="database not found"):
        write_intrinsics(tmp_path / "missing.db", {})
    text = tmp_path / "x.db"
    text.write_text("not a database\n" * 10)
    with pytest.raises(CalibrationError, match="not an SQLite database"):
        write_intrinsics(text, {})
