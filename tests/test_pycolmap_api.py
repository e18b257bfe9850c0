"""The API in pycolmap's terms: results as ``pycolmap.Camera``, ``apply`` to a reconstruction,
a database or a path, ``merge_cameras``, COLMAP's ``cameras.txt``, calibration from a
reconstruction's tracks (``calibrate_reconstruction``). The README's lines:
``test_reconstruct.py``; misuse: ``bad_input/test_pycolmap_workflow.py``.

Accuracy of the reconstruction route against ground truth: a synthetic scene here, the
Strecha scenes (``real_data``) against calibrating their database directly.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from conftest import database_rows, synthesize, synthesize_per_image

from colmap_trifocal import (
    CalibrationError,
    CalibrationOptions,
    calibrate_database,
    calibrate_reconstruction,
    merge_cameras,
    write_cameras_txt,
)
from colmap_trifocal.database.from_reconstruction import (
    MODEL_FOCAL_TOLERANCE,
    contents_from_reconstruction,
    grouping_cameras,
    track_matches,
)
from colmap_trifocal.database.snapshot import read_database
from colmap_trifocal.datasets.strecha import ground_truth_intrinsics
from colmap_trifocal.synthetic.demo import make_demo_database

#: ``(fx, fy, cx, cy)`` of ``conftest.synthesize``'s default camera (SIMPLE_RADIAL 1024x768).
SYNTHETIC_SIZE = (1024, 768)


def mean_relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean(np.abs(np.asarray(estimate) / truth - 1)))


def _map(database: Path, folder: Path) -> pycolmap.Reconstruction:
    """pycolmap's incremental mapping of ``database`` (one thread): its largest model."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    models = pycolmap.incremental_mapping(database, folder / "images", folder / "sparse", options)
    assert models, "mapping gave no model"
    return max(models.values(), key=lambda m: m.num_reg_images())


@pytest.fixture(scope="module")
def demo_model(tmp_path_factory: pytest.TempPathFactory) -> tuple[pycolmap.Reconstruction, Path]:
    """The demo scene (10 images, 0.5 px noise, 20 % wrong matches, camera 5 % off),
    mapped by pycolmap; the model and the database."""
    folder = tmp_path_factory.mktemp("demo_model")
    database = folder / "database.db"
    make_demo_database(database, seed=0)
    return _map(database, folder), database


# --------------------------------------------------------------------------- tracks → matches


def test_track_matches_pairs_every_two_observations() -> None:
    observations = np.array(
        [
            # point 7 seen by images 3, 1, 2 (keypoints 30, 10, 20): three pairs
            [7, 3, 30],
            [7, 1, 10],
            [7, 2, 20],
            # point 9 seen twice in image 2 (keypoints 5 and 4) and in image 1: one pair,
            # the smaller keypoint index kept
            [9, 2, 5],
            [9, 1, 11],
            [9, 2, 4],
            # point 4 seen once: no match
            [4, 3, 1],
        ]
    )
    matches = track_matches(observations)
    assert sorted(matches) == [(1, 2), (1, 3), (2, 3)]
    np.testing.assert_array_equal(matches[(1, 2)], [[10, 20], [11, 4]])
    np.testing.assert_array_equal(matches[(1, 3)], [[10, 30]])
    np.testing.assert_array_equal(matches[(2, 3)], [[20, 30]])
    assert all(m.dtype == np.int32 for m in matches.values())
    assert track_matches(np.zeros((0, 3))) == {}


def test_reconstruction_contents_are_the_databases(tmp_path: Path) -> None:
    """pycolmap's synthetic database holds every common track of a pair as verified
    matches: read from the model, the same keypoints and the same matches."""
    reconstruction = synthesize(tmp_path / "s.db", frames=6, points=400)
    database = read_database(tmp_path / "s.db")
    contents = contents_from_reconstruction(reconstruction)
    assert contents.image_camera == database.image_camera
    assert contents.image_names == database.image_names
    for image_id, xy in database.keypoints.items():
        np.testing.assert_allclose(contents.keypoints[image_id], xy, atol=1e-3)
    assert sorted(contents.matches) == sorted(database.matches)
    for pair, matches in database.matches.items():
        assert set(map(tuple, contents.matches[pair])) == set(map(tuple, matches))


def test_too_few_registered_images(tmp_path: Path) -> None:
    reconstruction = synthesize(tmp_path / "s.db", frames=6, points=100)
    for image_id in sorted(reconstruction.reg_image_ids())[2:]:
        reconstruction.deregister_frame(reconstruction.image(image_id).frame_id)
    with pytest.raises(CalibrationError, match="2 registered image"):
        calibrate_reconstruction(reconstruction)


def test_non_finite_keypoints(tmp_path: Path) -> None:
    reconstruction = synthesize(tmp_path / "s.db", frames=6, points=100)
    image = reconstruction.image(3)
    image.points2D[5].xy = np.array([np.nan, 10.0])
    with pytest.raises(CalibrationError, match="image 3 .* NaN or infinite"):
        calibrate_reconstruction(reconstruction)


def test_model_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="model folder not found"):
        calibrate_reconstruction(tmp_path / "nope")
    with pytest.raises(CalibrationError, match="not a COLMAP model"):
        calibrate_reconstruction(tmp_path)
    reconstruction = synthesize(tmp_path / "s.db", frames=6, points=100)
    with pytest.raises(CalibrationError, match="options.write"):
        calibrate_reconstruction(reconstruction, CalibrationOptions(write=True))


# --------------------------------------------------------------------------- results as cameras


def test_camera_is_a_pycolmap_camera_with_the_estimate(tmp_path: Path) -> None:
    """SIMPLE_RADIAL with a stored k: the camera keeps model, size, id and k; f is the
    estimate's (fx + fy) / 2 and the principal point the estimate's."""
    database = tmp_path / "radial.db"
    synthesize(database, "SIMPLE_RADIAL", [1100.0, 500.0, 380.0, -0.02], frames=8, points=500)
    (result,) = calibrate_database(database)
    camera = result.camera
    assert isinstance(camera, pycolmap.Camera)
    assert (camera.model.name, camera.width, camera.height) == ("SIMPLE_RADIAL", *SYNTHETIC_SIZE)
    assert camera.camera_id == result.camera_id
    np.testing.assert_allclose(
        camera.params, [(result.fx + result.fy) / 2, result.cx, result.cy, -0.02]
    )
    np.testing.assert_allclose(camera.params[:3], [1100.0, 500.0, 380.0], rtol=1e-3)


def _per_image_database(path: Path, images: int = 8) -> pycolmap.Reconstruction:
    """One SIMPLE_RADIAL camera per image with equal params (COLMAP's default), 0.5 px noise."""
    return synthesize_per_image(path, images, points=500, noise=0.5)


def test_apply_writes_every_camera_of_the_group(tmp_path: Path) -> None:
    database = tmp_path / "per_image.db"
    truth = _per_image_database(database)
    (result,) = calibrate_database(database)
    assert len(result.camera_ids) == 8
    model = pycolmap.Reconstruction(truth)
    for camera in model.cameras.values():  # something else than the estimate
        camera.params = [900.0, 400.0, 300.0, 0.01]
    assert result.apply(model) == result.camera_ids
    for camera_id in result.camera_ids:
        stored_k = truth.cameras[camera_id].params[3]  # the database's, kept
        np.testing.assert_allclose(
            model.cameras[camera_id].params,
            [(result.fx + result.fy) / 2, result.cx, result.cy, stored_k],
        )
    np.testing.assert_allclose(result.camera.params, model.cameras[result.camera_id].params)


def test_apply_refuses_other_cameras(tmp_path: Path) -> None:
    """A camera id the model lacks, or another size: refused, nothing written."""
    database = tmp_path / "per_image.db"
    truth = _per_image_database(database, images=6)
    (result,) = calibrate_database(database)
    before = {c: np.array(cam.params) for c, cam in truth.cameras.items()}

    other_size = pycolmap.Reconstruction(truth)
    other_size.cameras[result.camera_ids[-1]].width = 2048
    missing = pycolmap.Reconstruction()
    for camera_id in (1, 2, 3):
        missing.add_camera(truth.cameras[camera_id])
    for reconstruction, message in (
        (other_size, "is a SIMPLE_RADIAL 2048x768, the calibrated one a SIMPLE_RADIAL 1024x768"),
        (missing, "has no camera 4"),
    ):
        with pytest.raises(CalibrationError, match=message):
            result.apply(reconstruction)
        for camera_id, camera in reconstruction.cameras.items():
            np.testing.assert_array_equal(camera.params, before[camera_id])


# --------------------------------------------------------------------------- from a reconstruction


def test_calibrate_reconstruction_synthetic_accuracy(demo_model, tmp_path: Path) -> None:
    """The demo scene mapped by pycolmap (its camera: f refined, the principal point left
    5 % off): from the model's tracks within 0.2 % of the truth, as from the database."""
    reconstruction, database = demo_model
    truth = np.array([1400.0, 1420.0, 790.0, 612.0])
    model_camera = reconstruction.cameras[1]
    given = np.array(model_camera.params)
    (result,) = calibrate_reconstruction(reconstruction, CalibrationOptions(seed=0))
    np.testing.assert_array_equal(reconstruction.cameras[1].params, given)  # not changed
    np.testing.assert_allclose(result.reference, given)
    assert mean_relative_error(result.reference, truth) > 0.015  # the model's pp is off
    error = mean_relative_error(result.intrinsics, truth)
    (direct,) = calibrate_database(database, CalibrationOptions(seed=0))
    assert error <= 0.002, (result.intrinsics, mean_relative_error(direct.intrinsics, truth))
    assert result.to_json()["reference"] == dict(zip(("fx", "fy", "cx", "cy"), given, strict=True))
    assert "model" in result.compare_with_model()

    # The same from the folder, binary and text.
    binary, text = tmp_path / "bin", tmp_path / "txt"
    binary.mkdir()
    text.mkdir()
    reconstruction.write(binary)
    reconstruction.write_text(text)
    for folder in (binary, text):
        (again,) = calibrate_reconstruction(folder, CalibrationOptions(seed=0))
        np.testing.assert_allclose(again.intrinsics, result.intrinsics, rtol=1e-6)


def test_reconstruction_groups_per_image_cameras(tmp_path: Path) -> None:
    """Mapping refines each of COLMAP's per-image cameras on its own: their params differ,
    and ``auto`` still calibrates them as one camera."""
    database = tmp_path / "per_image.db"
    truth = _per_image_database(database)
    model = _map(database, tmp_path)
    params = np.array([c.params for c in model.cameras.values()])
    assert len(params) == 8 and len(np.unique(params, axis=0)) > 1
    focal = params[:, 0]
    assert focal.max() / focal.min() - 1 < MODEL_FOCAL_TOLERANCE
    (result,) = calibrate_reconstruction(model)
    assert result.camera_ids == sorted(model.cameras)
    true = np.array(truth.cameras[1].params)
    assert mean_relative_error(result.intrinsics, true[[0, 0, 1, 2]]) < 0.005
    # ``camera``: one group per id, of one image each.
    with pytest.raises(CalibrationError, match="no camera has at least 3 images"):
        calibrate_reconstruction(model, CalibrationOptions(group="camera"))


def test_grouping_cameras_splits_other_lenses() -> None:
    from colmap_trifocal.database.cameras import CameraInfo

    def camera(camera_id: int, focal: float, width: int = 1000) -> CameraInfo:
        return CameraInfo(camera_id, "SIMPLE_RADIAL", width, 800, [focal, 500, 400, 0])

    cameras = {
        1: camera(1, 1000.0),
        2: camera(2, 1030.0),
        3: camera(3, 1200.0),  # another lens
        4: camera(4, 1010.0, width=1200),  # another sensor size
        5: camera(5, 1190.0),
    }
    grouped = grouping_cameras(cameras)
    key = {c: grouped[c].params.tobytes() + bytes(grouped[c].width) for c in cameras}
    assert key[1] == key[2] != key[3] == key[5]
    assert key[4] not in (key[1], key[3])


# --------------------------------------------------------------------------- pycolmap targets


def test_cameras_are_pycolmap_cameras_of_every_id(tmp_path: Path) -> None:
    database = tmp_path / "per_image.db"
    _per_image_database(database, images=6)
    (result,) = calibrate_database(database)
    cameras = result.cameras
    assert sorted(cameras) == result.camera_ids
    for camera_id, camera in cameras.items():
        assert isinstance(camera, pycolmap.Camera) and camera.camera_id == camera_id
        np.testing.assert_array_equal(camera.params, result.camera.params)


def test_apply_to_an_open_database_and_to_a_path(tmp_path: Path) -> None:
    """An open ``pycolmap.Database`` gets the estimate in one transaction; a path through
    the safe write (a backup with the rows as they were, then the new params)."""
    database = tmp_path / "per_image.db"
    _per_image_database(database, images=6)
    (result,) = calibrate_database(database)
    opened = tmp_path / "opened.db"
    opened.write_bytes(database.read_bytes())
    with pycolmap.Database.open(str(opened)) as db:
        assert result.apply(db) == result.camera_ids
        stored = {c.camera_id: np.array(c.params) for c in db.read_all_cameras()}
    for camera_id, camera in result.cameras.items():
        np.testing.assert_array_equal(stored[camera_id], camera.params)

    before = database_rows(database)
    assert result.apply(str(database)) == result.camera_ids
    assert database_rows(database.with_name("per_image.db.bak")) == before
    for camera in read_database(database).cameras.values():
        np.testing.assert_array_equal(camera.params, result.cameras[camera.camera_id].params)


def test_merge_cameras_in_a_reconstruction(tmp_path: Path) -> None:
    """A merged copy: one camera for the group, the same poses, points and observations,
    an unregistered image kept; the given reconstruction unchanged. ``apply`` then writes
    the group's first camera only, and bundle adjustment runs on it."""
    database = tmp_path / "per_image.db"
    truth = _per_image_database(database)
    (result,) = calibrate_database(database)
    model = pycolmap.Reconstruction(truth)
    unregistered = sorted(model.reg_frame_ids())[-1]
    model.deregister_frame(unregistered)
    merged = merge_cameras(model, result.camera_ids)
    assert len(model.cameras) == 8  # the given one as it was
    assert sorted(merged.cameras) == [result.camera_id]
    assert {image.camera_id for image in merged.images.values()} == {result.camera_id}
    assert (merged.num_images(), merged.num_reg_images()) == (8, 7)
    assert merged.num_points3D() == model.num_points3D()
    for image_id in model.reg_image_ids():
        np.testing.assert_allclose(
            merged.image(image_id).cam_from_world().matrix(),
            model.image(image_id).cam_from_world().matrix(),
        )
    assert merged.compute_mean_reprojection_error() == pytest.approx(
        model.compute_mean_reprojection_error()
    )
    assert result.apply(merged) == [result.camera_id]
    np.testing.assert_array_equal(merged.cameras[result.camera_id].params, result.camera.params)
    pycolmap.bundle_adjustment(merged, pycolmap.BundleAdjustmentOptions())
    assert merged.compute_mean_reprojection_error() < 1.0  # px, 0.5 px keypoint noise


def test_merge_cameras_in_a_database(tmp_path: Path) -> None:
    """In place after a backup: one camera for the group, every image on it, and the
    calibration of the merged database the same camera."""
    database = tmp_path / "per_image.db"
    _per_image_database(database, images=6)
    (before_merge,) = calibrate_database(database)
    rows = database_rows(database)
    assert merge_cameras(database, before_merge.camera_ids) is None
    assert database_rows(database.with_name("per_image.db.bak")) == rows
    contents = read_database(database)
    assert sorted(contents.cameras) == [before_merge.camera_id]
    assert set(contents.image_camera.values()) == {before_merge.camera_id}
    (after,) = calibrate_database(database)
    assert after.camera_ids == [before_merge.camera_id]
    np.testing.assert_allclose(after.intrinsics, before_merge.intrinsics, rtol=1e-9)


def test_write_cameras_txt_is_read_back_by_pycolmap(tmp_path: Path) -> None:
    """COLMAP's text cameras: pycolmap reads every camera id back, params bit for bit."""
    database = tmp_path / "per_image.db"
    _per_image_database(database, images=6)
    results = calibrate_database(database)
    folder = tmp_path / "text"
    folder.mkdir()
    assert write_cameras_txt(results, folder / "cameras.txt") == folder / "cameras.txt"
    (folder / "images.txt").write_text("")
    (folder / "points3D.txt").write_text("")
    model = pycolmap.Reconstruction(folder)
    (result,) = results
    assert sorted(model.cameras) == result.camera_ids
    for camera_id, camera in result.cameras.items():
        assert model.cameras[camera_id].model == camera.model
        np.testing.assert_array_equal(model.cameras[camera_id].params, camera.params)
    text = (folder / "cameras.txt").read_text()
    assert text.startswith("# Camera list") and "# Number of cameras: 6" in text


# --------------------------------------------------------------------------- real data


@pytest.mark.slow  # builds the scene's database and model on first use (1-2 min)
@pytest.mark.real_data
@pytest.mark.parametrize("scene", ["fountain-P11", "Herz-Jesus-P8"])
def test_strecha_model_route(scene: str, strecha_model: Callable) -> None:
    """From pycolmap's incremental model of the scene's database (COLMAP's default
    camera, f refined, principal point left at the centre, 0.7 % off): within 0.5 % of
    the ground truth, and better than the model's own intrinsics."""
    model, database, folder = strecha_model(scene)
    truth = ground_truth_intrinsics(folder)
    (result,) = calibrate_reconstruction(model, CalibrationOptions(seed=0))
    error = mean_relative_error(result.intrinsics, truth)
    assert error <= 0.005, result.compare_with_model()
    assert error < mean_relative_error(result.reference, truth)
    assert result.num_inlier_triplets >= 0.75 * result.num_triplets
