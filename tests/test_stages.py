"""The calibration's stages and what they reuse: per-stage seconds, carried-over tensors,
the polish's information on the shared camera."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.cli import main
from colmap_trifocal.common.bundle_adjustment import bundle_adjustment_options
from colmap_trifocal.common.timing import STAGES
from colmap_trifocal.geometry.trifocal import intrinsics_matrix
from colmap_trifocal.geometry.triplet_fit import estimate_triplet_tensor
from colmap_trifocal.intrinsics.polish.information import reduced_information
from colmap_trifocal.intrinsics.solve.constraints import ConstraintProblem
from colmap_trifocal.intrinsics.solve.theta import intrinsics_to_theta
from colmap_trifocal.intrinsics.tensors.estimator import MAX_STARTS_PER_TRIPLET
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.demo import make_demo_database
from colmap_trifocal.synthetic.facade import facade_scene
from colmap_trifocal.synthetic.lenses import with_radial_distortion

VIEWS = (0, 4, 8)


def _tracks(scene, views=VIEWS) -> np.ndarray:
    """Pixel tracks (3, n, 2) of the points every view sees (outlier tracks left out)."""
    seen = np.all(scene.visible[list(views)], axis=0) & ~scene.outliers
    return scene.observations[list(views)][:, seen]


def test_tensor_carried_to_a_new_start_equals_the_one_estimated_there() -> None:
    """Renormalising is exact, and it is what re-estimation from the new start reaches."""
    scene = facade_scene(relief=0.3, seed=1, noise_px=1.0, num_points=600)
    x = _tracks(scene)
    truth = scene.intrinsics
    old, new = truth * [1.05, 0.96, 1.03, 0.98], truth * [0.97, 1.02, 0.99, 1.01]
    estimated_old = estimate_triplet_tensor(
        (1, 2, 3), x, intrinsics_matrix(old), np.random.default_rng(0)
    )
    estimated_new = estimate_triplet_tensor(
        (1, 2, 3), x, intrinsics_matrix(new), np.random.default_rng(0)
    )
    assert estimated_old is not None and estimated_new is not None
    carried = estimated_old.renormalised(intrinsics_matrix(old), intrinsics_matrix(new))
    for K in (truth, truth * 1.01):
        theta_old, theta_new = intrinsics_to_theta(K, old), intrinsics_to_theta(K, new)
        before = ConstraintProblem.build([estimated_old], theta_old).norms(theta_old)
        after = ConstraintProblem.build([carried], theta_new).norms(theta_new)
        again = ConstraintProblem.build([estimated_new], theta_new).norms(theta_new)
        np.testing.assert_allclose(after, before, rtol=1e-7)
        np.testing.assert_allclose(again, after, rtol=1e-3)
    assert np.isclose(np.linalg.norm(carried.tensor), 1.0)


def _one_triplet_reconstruction(scene, views=VIEWS, model="PINHOLE", params=None):
    """A pycolmap reconstruction of three views of a scene (true poses, noisy pixels)."""
    seen = np.all(scene.visible[list(views)], axis=0) & ~scene.outliers
    pixels = scene.observations[list(views)][:, seen]
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(
            camera_id=1,
            model=model,
            width=scene.width,
            height=scene.height,
            params=[float(v) for v in (scene.intrinsics if params is None else params)],
        )
    )
    for view, index in enumerate(views):
        image = pycolmap.Image(
            name=f"{view}.png",
            keypoints=np.ascontiguousarray(pixels[view]),
            camera_id=1,
            image_id=view + 1,
        )
        pose = pycolmap.Rigid3d(
            pycolmap.Rotation3d(scene.rotations[index]), scene.translations[index]
        )
        reconstruction.add_image_with_trivial_frame(image, pose)
    point_ids = [
        reconstruction.add_point3D(
            point, pycolmap.Track([pycolmap.TrackElement(i, k) for i in (1, 2, 3)])
        )
        for k, point in enumerate(scene.points[seen])
    ]
    return reconstruction, pixels, point_ids


def test_triplet_information_matches_pycolmaps_covariance() -> None:
    """H of one triplet (poses and points eliminated) against pycolmap's BA covariance."""
    scene = facade_scene(relief=0.3, seed=2, noise_px=1.0, num_points=400)
    reconstruction, pixels, point_ids = _one_triplet_reconstruction(scene)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in (1, 2, 3):
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = bundle_adjustment_options(
        refine_focal_length=True,
        refine_principal_point=True,
        function_tolerance=1e-12,
        threads=1,
    )
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)
    assert adjuster.solve().is_solution_usable()
    covariance = pycolmap.estimate_ba_covariance(
        pycolmap.BACovarianceOptions(), reconstruction, adjuster
    )
    camera_block = covariance.get_other_params_cov(reconstruction.cameras[1].params)
    intrinsics = np.asarray(reconstruction.cameras[1].params)
    poses = np.stack(
        [np.asarray(reconstruction.images[i].cam_from_world().matrix()) for i in (1, 2, 3)]
    )
    points = np.array([reconstruction.points3D[p].xyz for p in point_ids])
    H, gradient, cost = reduced_information(intrinsics, poses, points, pixels)
    np.testing.assert_allclose(
        np.sqrt(np.diag(np.linalg.inv(H))), np.sqrt(np.diag(camera_block)), rtol=0.01
    )
    # At the optimum the reduced gradient vanishes (relative to the information).
    assert np.all(np.abs(np.linalg.solve(H, gradient)) < 1e-3 * np.sqrt(np.diag(np.linalg.inv(H))))
    assert cost == pytest.approx(2 * adjuster.solve().ceres_summary.final_cost, rel=1e-6)


def test_radial_triplet_information_matches_pycolmaps_covariance() -> None:
    """The same with a SIMPLE_RADIAL camera (f, cx, cy, k): H on (fx, fy, cx, cy, k)
    reduced to the single focal length matches pycolmap's covariance of (f, cx, cy, k)."""
    scene = with_radial_distortion(facade_scene(relief=0.3, seed=2, num_points=400), -0.08)
    f, cx, cy = scene.intrinsics[0], scene.intrinsics[2], scene.intrinsics[3]
    reconstruction, pixels, point_ids = _one_triplet_reconstruction(
        scene, model="SIMPLE_RADIAL", params=[f, cx, cy, 0.0]
    )
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in (1, 2, 3):
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = bundle_adjustment_options(
        refine_focal_length=True,
        refine_principal_point=True,
        refine_extra_params=True,
        function_tolerance=1e-12,
        threads=1,
    )
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)
    assert adjuster.solve().is_solution_usable()
    camera = reconstruction.cameras[1]
    assert camera.params[3] == pytest.approx(-0.08, abs=0.02)  # the lens is found
    covariance = pycolmap.estimate_ba_covariance(
        pycolmap.BACovarianceOptions(), reconstruction, adjuster
    )
    camera_block = covariance.get_other_params_cov(camera.params)
    f, cx, cy, k = camera.params
    poses = np.stack(
        [np.asarray(reconstruction.images[i].cam_from_world().matrix()) for i in (1, 2, 3)]
    )
    points = np.array([reconstruction.points3D[p].xyz for p in point_ids])
    H, _, cost = reduced_information(
        np.array([f, f, cx, cy]), poses, points, pixels, radial=np.array([k])
    )
    single = np.array(
        [[1.0, 0, 0, 0], [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    )
    reduced = single.T @ H @ single
    np.testing.assert_allclose(
        np.sqrt(np.diag(np.linalg.inv(reduced))), np.sqrt(np.diag(camera_block)), rtol=0.01
    )
    assert cost == pytest.approx(2 * adjuster.solve().ceres_summary.final_cost, rel=1e-6)


def test_stage_seconds_and_tensor_work_in_the_json(tmp_path: Path) -> None:
    database = tmp_path / "demo.db"
    make_demo_database(database, seed=0)
    report = tmp_path / "out.json"
    assert main(["calibrate", str(database), "--json", str(report)]) == 0
    (entry,) = json.loads(report.read_text())
    stages = entry["stage_seconds"]
    assert list(stages) == [*STAGES, "total"]
    assert all(value >= 0 for value in stages.values())
    assert stages["total"] == pytest.approx(sum(stages[s] for s in STAGES), abs=1e-3)
    assert stages["total"] == pytest.approx(entry["seconds"], abs=1e-3)
    assert stages["tensors"] > 0 and stages["focal_search"] > 0
    assert 0 < entry["tensor_starts"] <= MAX_STARTS_PER_TRIPLET * entry["num_triplets"]
    truth = np.array([1400.0, 1420.0, 790.0, 612.0])
    estimate = np.array([entry[name] for name in ("fx", "fy", "cx", "cy")])
    assert np.mean(np.abs(estimate / truth - 1)) < 0.002


def test_restart_carries_over_the_agreeing_tensors() -> None:
    """From a start 8 % off the estimate moves far and the tensors are estimated again
    from it: the agreeing ones are carried over, so fewer than two full sets are run."""
    scene = facade_scene(relief=0.3, seed=0, noise_px=1.0, num_points=800)
    truth = scene.intrinsics
    options = CalibrationOptions(
        prior=tuple(truth * [1.08, 1.08, 1.0, 1.0]), focal_search=False, seed=0
    )
    (result,) = calibrate_contents(scene_contents(scene), options)
    assert not np.allclose(result.start, options.prior)  # it restarted
    assert result.tensor_starts < 2 * result.num_triplets
    assert np.mean(np.abs(result.intrinsics / truth - 1)) < 0.002
