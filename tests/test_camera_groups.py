"""Physical cameras: grouping camera ids, calibrating a group, writing all its cameras,
schema variants (COLMAP 3.12+ rigs/frames and the older schema), EXIF priors, -v, --model."""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import CliResult, synthesize, synthesize_per_image

from colmap_trifocal import CalibrationError
from colmap_trifocal.database.camera_groups import format_ids, group_cameras
from colmap_trifocal.database.cameras import CameraInfo
from colmap_trifocal.database.shared_cameras import merge_group_cameras
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.intrinsics.api import (
    CalibrationOptions,
    calibrate_contents_methods,
    calibrate_database,
    calibrate_groups,
)
from colmap_trifocal.intrinsics.pipeline import calibrate_camera

#: SIMPLE_RADIAL (f, cx, cy, k) of pycolmap's synthetic cameras.
SIMPLE_RADIAL = [1280.0, 512.0, 384.0, 0.05]
TRUTH = np.array([1280.0, 1280.0, 512.0, 384.0])
#: A prior 4-6 % off the truth.
PRIOR = (1340.0, 1340.0, 530.0, 370.0)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _camera(camera_id: int, params=(1000.0, 500.0, 400.0, 0.0), size=(1000, 800), **kw):
    return CameraInfo(camera_id, "SIMPLE_RADIAL", size[0], size[1], np.array(params), **kw)


def per_image_database(path: Path, images: int = 6, points: int = 400) -> pycolmap.Reconstruction:
    """Synthetic database as COLMAP's default makes it: one camera (and rig) per image,
    all with the same parameters."""
    return synthesize_per_image(path, images, points, SIMPLE_RADIAL)


# --------------------------------------------------------------------------- grouping (pure)


def test_auto_groups_equal_cameras_and_keeps_different_ones_apart() -> None:
    cameras = {
        1: _camera(1),
        2: _camera(2),
        3: _camera(3, params=(1100.0, 500.0, 400.0, 0.0)),  # another zoom setting
        4: _camera(4, size=(800, 1000)),  # portrait
        5: _camera(5, has_prior_focal_length=True),  # focal length from EXIF
        6: _camera(6),
        7: _camera(7),  # no images: left out
    }
    image_camera = {10: 1, 11: 2, 12: 3, 13: 4, 14: 5, 15: 6, 16: 1}
    groups = group_cameras(cameras, image_camera, "auto")
    assert [g.camera_ids for g in groups] == [(1, 2, 6), (3,), (4,), (5,)]
    assert groups[0].image_ids == (10, 11, 15, 16)
    assert groups[0].camera_id == 1
    per_camera = group_cameras(cameras, image_camera, "camera")
    assert [g.camera_ids for g in per_camera] == [(1,), (2,), (3,), (4,), (5,), (6,)]
    assert per_camera[0].image_ids == (10, 16)


def test_auto_never_merges_sensors_of_one_rig() -> None:
    cameras = {c: _camera(c) for c in (1, 2, 3, 4)}
    image_camera = {10: 1, 11: 2, 12: 3, 13: 4}
    groups = group_cameras(cameras, image_camera, "auto", rig_sensor_cameras={1, 2})
    assert [g.camera_ids for g in groups] == [(1,), (2,), (3, 4)]


def test_all_groups_everything_of_one_size_and_refuses_mixed_sizes() -> None:
    cameras = {1: _camera(1), 2: _camera(2, params=(900.0, 510.0, 390.0, 0.01))}
    (group,) = group_cameras(cameras, {10: 1, 11: 2, 12: 2}, "all")
    assert group.camera_ids == (1, 2) and group.image_ids == (10, 11, 12)
    cameras[3] = _camera(3, size=(640, 480))
    with pytest.raises(CalibrationError, match="one camera model and image size"):
        group_cameras(cameras, {10: 1, 11: 2, 12: 3}, "all")
    with pytest.raises(CalibrationError, match="unknown grouping"):
        group_cameras(cameras, {10: 1}, "physical")


def test_format_ids() -> None:
    assert format_ids((1, 2, 3, 7)) == "1-3, 7"
    assert format_ids([5]) == "5"
    assert format_ids([1, 3, 4, 5, 9, 10]) == "1, 3-5, 9-10"


# --------------------------------------------------------------------------- calibration


def test_colmap_default_database_is_calibrated_as_one_camera(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    per_image_database(path)
    contents = read_database(path)
    assert len(contents.cameras) == 6 and len(contents.image_names) == 6
    options = CalibrationOptions(prior=PRIOR, workers=1)
    (result,) = calibrate_database(path, options)
    assert result.camera_ids == [1, 2, 3, 4, 5, 6]
    assert result.camera_id == 1
    np.testing.assert_allclose(result.intrinsics, TRUTH, rtol=1e-5)
    # The tensors come from images of different camera ids.
    assert len({i for t in result.tensors for i in t.image_ids}) == 6
    # Per camera id there is nothing to calibrate: the old behaviour, now explained.
    with pytest.raises(CalibrationError, match="no camera has at least 3 images"):
        calibrate_database(path, CalibrationOptions(prior=PRIOR, group="camera"))
    # --camera-id selects the whole group of that camera.
    (selected,) = calibrate_database(path, CalibrationOptions(prior=PRIOR, camera_ids=[4]))
    assert selected.camera_ids == [1, 2, 3, 4, 5, 6]


def test_grouped_result_equals_single_camera_database(tmp_path: Path) -> None:
    """The same keypoints and matches with one shared camera id give the same estimate."""
    grouped = tmp_path / "grouped.db"
    per_image_database(grouped)
    single = tmp_path / "single.db"
    single.write_bytes(grouped.read_bytes())
    assert merge_group_cameras(single, [[1, 2, 3, 4, 5, 6]]) == 5
    merged = read_database(single)
    assert list(merged.cameras) == [1] and set(merged.image_camera.values()) == {1}
    with pycolmap.Database.open(str(single)) as db:  # the rig tables stay consistent
        assert db.num_rigs() == 1 and db.num_frames() == 6
        assert {f.rig_id for f in db.read_all_frames()} == {1}
    options = CalibrationOptions(prior=PRIOR, seed=3, workers=1)
    (a,) = calibrate_database(grouped, options)
    (b,) = calibrate_database(single, options)
    assert a.intrinsics.tobytes() == b.intrinsics.tobytes()


def test_write_updates_every_camera_of_the_group_keeping_distortion(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    per_image_database(path)
    con = sqlite3.connect(path)  # give each camera its own (stored) distortion
    con.execute(
        "UPDATE cameras SET params = ? WHERE camera_id = 2",
        (np.array([1280, 512, 384, 0.05000001]).tobytes(),),
    )
    con.commit()
    con.close()
    before = read_database(path).cameras
    results = calibrate_database(
        path, CalibrationOptions(prior=PRIOR, group="all", write=True, workers=1)
    )
    (result,) = results
    assert result.camera_ids == [1, 2, 3, 4, 5, 6]
    after = read_database(path).cameras
    for camera_id, camera in after.items():
        np.testing.assert_allclose(camera.intrinsics, result.intrinsics, rtol=1e-12)
        assert camera.distortion.tobytes() == before[camera_id].distortion.tobytes()
    assert (tmp_path / "database.db.bak").is_file()


def test_small_groups_are_skipped_while_others_calibrate(tmp_path: Path) -> None:
    path = tmp_path / "database.db"
    per_image_database(path, images=8)
    con = sqlite3.connect(path)  # images 7 and 8: another focal length (another camera)
    for camera_id in (7, 8):
        con.execute(
            "UPDATE cameras SET params = ? WHERE camera_id = ?",
            (np.array([1500.0, 512, 384, 0.05]).tobytes(), camera_id),
        )
    con.commit()
    con.close()
    results, skipped = calibrate_groups(
        read_database(path), CalibrationOptions(prior=PRIOR, workers=1), ("msac-opt",)
    )
    (result,) = results["msac-opt"]
    assert result.camera_ids == [1, 2, 3, 4, 5, 6]
    np.testing.assert_allclose(result.intrinsics, TRUTH, rtol=1e-5)
    (skip,) = skipped
    assert skip.to_json() == {
        "camera_id": 7,
        "camera_ids": [7, 8],
        "num_images": 2,
        "skipped": "2 images",
    }


def test_one_result_type_for_a_camera_and_its_group(tmp_path: Path) -> None:
    """A camera's result names the camera ids it is for: its own id as the calibration
    builds it, every id of the group once calibrate returns it (for each method), and
    that is what it writes and reports."""
    path = tmp_path / "database.db"
    per_image_database(path)
    contents = read_database(path)
    options = CalibrationOptions(prior=PRIOR, workers=1)
    (own,) = calibrate_camera(
        contents, contents.cameras[1], sorted(contents.image_names), options, ("fundamental",)
    ).values()
    assert own.camera_ids == [1] and list(own.updated_cameras()) == [1]
    assert own.to_json()["camera_ids"] == [1]
    by_method = calibrate_contents_methods(contents, options, ("msac", "fundamental"))
    for (result,) in by_method.values():
        assert result.camera_ids == [1, 2, 3, 4, 5, 6] and result.camera_id == 1
        assert sorted(result.updated_cameras()) == [1, 2, 3, 4, 5, 6]
        data = result.to_json()
        assert data["camera_ids"] == [1, 2, 3, 4, 5, 6] and data["start_source"] == "--prior"
        assert not {"tensors", "stored_camera", "group_cameras"} & set(data)
    msac, fundamental = (results[0] for results in by_method.values())
    assert msac.camera_ids is not fundamental.camera_ids  # each result its own lists


def test_cli_reports_skipped_group_in_json_and_on_stderr(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    path = tmp_path / "database.db"
    per_image_database(path, images=8)
    con = sqlite3.connect(path)
    con.execute(
        "UPDATE cameras SET params = ? WHERE camera_id = 8",
        (np.array([1500.0, 512, 384, 0.05]).tobytes(),),
    )
    con.commit()
    con.close()
    out = tmp_path / "out.json"
    prior = ",".join(map(str, PRIOR))
    result = run_main("calibrate", path, "--prior", prior, "--json", out, "--write")
    assert result.returncode == 0, result.stderr
    assert "warning: camera 8 skipped: 1 image" in result.stderr
    assert "wrote 7 camera(s)" in result.stdout
    assert "shared by camera ids 1-7" in result.stdout
    calibrated, skipped = json.loads(out.read_text())
    assert calibrated["camera_ids"] == [1, 2, 3, 4, 5, 6, 7]
    assert calibrated["start_source"] == "--prior"
    assert skipped == {"camera_id": 8, "camera_ids": [8], "num_images": 1, "skipped": "1 image"}
    stored = read_database(path).cameras
    assert stored[8].params.tolist() == [1500.0, 512, 384, 0.05]  # not written
    np.testing.assert_allclose(stored[7].intrinsics, TRUTH, rtol=1e-5)


def test_verbose_accepted_after_the_subcommand(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    path = tmp_path / "database.db"
    synthesize(path, "PINHOLE", [1100.0, 1250.0, 530.0, 370.0])
    base = ["calibrate", path, "--prior", "1140,1210,545,360"]
    for extra, expected in (([], False), (["-v"], True), (["-vv"], True), ([], False)):
        done = run_main(*base, *extra)
        assert done.returncode == 0, done.stderr
        assert ("INFO colmap_trifocal: read" in done.stderr) == expected, extra


def test_exif_prior_is_the_start_and_is_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "database.db"
    per_image_database(path)
    con = sqlite3.connect(path)  # as pycolmap stores an EXIF focal length (5 % off here)
    con.execute(
        "UPDATE cameras SET prior_focal_length = 1, params = ?",
        (np.array([1344.0, 512, 384, 0.05]).tobytes(),),
    )
    con.commit()
    con.close()
    assert all(c.has_prior_focal_length for c in read_database(path).cameras.values())
    with caplog.at_level("INFO", logger="colmap_trifocal"):
        (result,) = calibrate_database(path, CalibrationOptions(workers=1))
    assert result.start_source == "EXIF focal length"
    assert result.to_json()["start_source"] == "EXIF focal length"
    assert result.prior[0] == 1344.0
    assert "starting from the EXIF focal length 1344.0 px" in caplog.text
    # The focal search corrects the start (not exact: the keypoints were undistorted with
    # the stored, wrong focal length).
    np.testing.assert_allclose(result.intrinsics, TRUTH, rtol=1e-4)


# --------------------------------------------------------------------------- schema variants

#: COLMAP's schema before 3.12 (no rigs/frames/pose_priors; pose priors in ``images``).
OLD_SCHEMA = """
CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
    model INTEGER NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB,
    prior_focal_length INTEGER NOT NULL);
CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL,
    name TEXT NOT NULL UNIQUE, camera_id INTEGER NOT NULL, prior_qw REAL, prior_qx REAL,
    prior_qy REAL, prior_qz REAL, prior_tx REAL, prior_ty REAL, prior_tz REAL,
    CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
    FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
    cols INTEGER NOT NULL, data BLOB,
    FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
    cols INTEGER NOT NULL, data BLOB,
    FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
    cols INTEGER NOT NULL, data BLOB);
CREATE TABLE two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL,
    rows INTEGER NOT NULL, cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL,
    F BLOB, E BLOB, H BLOB, qvec BLOB, tvec BLOB);
"""


def old_schema_copy(new: Path, old: Path) -> None:
    """Rewrite a pycolmap 4.2 (COLMAP 3.12+) database in the pre-3.12 schema."""
    con = sqlite3.connect(old)
    con.executescript(OLD_SCHEMA)
    con.execute("ATTACH DATABASE ? AS new", (str(new),))
    con.executescript(
        """
        INSERT INTO cameras SELECT camera_id, model, width, height, params, prior_focal_length
            FROM new.cameras;
        INSERT INTO images (image_id, name, camera_id)
            SELECT image_id, name, camera_id FROM new.images;
        INSERT INTO keypoints SELECT * FROM new.keypoints;
        INSERT INTO descriptors SELECT image_id, rows, cols, data FROM new.descriptors;
        INSERT INTO matches SELECT * FROM new.matches;
        INSERT INTO two_view_geometries
            SELECT pair_id, rows, cols, data, config, F, E, H, qvec, tvec
            FROM new.two_view_geometries;
        """
    )
    con.commit()
    con.execute("DETACH DATABASE new")
    con.close()


def _tables(path: Path) -> set[str]:
    con = sqlite3.connect(path)
    try:
        return {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    finally:
        con.close()


@pytest.mark.parametrize("schema", ["3.12+", "pre-3.12"])
def test_schema_variants(schema: str, tmp_path: Path) -> None:
    new = tmp_path / "new.db"
    per_image_database(new)
    path = new
    if schema == "pre-3.12":
        path = tmp_path / "old.db"
        old_schema_copy(new, path)
        assert not _tables(path) & {"rigs", "rig_sensors", "frames", "frame_data"}
    else:
        assert {"rigs", "rig_sensors", "frames", "frame_data"} <= _tables(path)
    before = _sha256(path)
    options = CalibrationOptions(prior=PRIOR, workers=1)
    (result,) = calibrate_database(path, options)
    assert _sha256(path) == before  # read without a change (no migration of the user's file)
    assert result.camera_ids == [1, 2, 3, 4, 5, 6]
    np.testing.assert_allclose(result.intrinsics, TRUTH, rtol=1e-5)
    calibrate_database(path, replace(options, write=True))
    tables = _tables(path)
    assert ("rigs" in tables) == (schema == "3.12+")  # written in place, schema kept
    for camera in read_database(path).cameras.values():
        np.testing.assert_allclose(camera.intrinsics, result.intrinsics, rtol=1e-12)


def test_merge_group_cameras_on_the_old_schema(tmp_path: Path) -> None:
    new = tmp_path / "new.db"
    per_image_database(new)
    old = tmp_path / "old.db"
    old_schema_copy(new, old)
    assert merge_group_cameras(old, [[1, 2, 3, 4, 5, 6]]) == 5
    contents = read_database(old)
    assert list(contents.cameras) == [1] and set(contents.image_camera.values()) == {1}


# --------------------------------------------------------------------------- into a model


def test_calibrate_into_a_copy_of_a_model(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    path = tmp_path / "database.db"
    truth_model = per_image_database(path, points=600)
    model = tmp_path / "model"
    model.mkdir()
    wrong = pycolmap.Reconstruction(truth_model)
    for camera in wrong.cameras.values():  # a model built with a focal length 5 % off
        camera.params = [1344.0, 520.0, 380.0, 0.05]
    wrong.write(model)
    before = {p.name: _sha256(p) for p in model.iterdir()}
    output, report = tmp_path / "calibrated", tmp_path / "out.json"
    prior = ",".join(map(str, PRIOR))
    args = ["calibrate", path, "--prior", prior, "--model", model]
    result = run_main(*args, "--output", output, "--json", report)
    assert result.returncode == 0, result.stderr
    assert "mean reprojection error" in result.stdout
    assert {p.name: _sha256(p) for p in model.iterdir()} == before  # the input model is kept
    errors = json.loads(report.read_text())[0]["model"]["reprojection_error_px"]
    assert errors["with_estimate"] < errors["given"]
    assert errors["refined"] <= errors["with_estimate"] + 1e-9
    written = pycolmap.Reconstruction(output)
    for camera in written.cameras.values():
        fx, cx, cy = camera.params[:3]
        np.testing.assert_allclose([fx, fx, cx, cy], TRUTH, rtol=1e-4)
        assert camera.params[3] == pytest.approx(0.05)  # distortion not refined by default
    # The refusals of --model/--output/--refine are rows of the bad-input table (tests/bad_input/).
