"""Planar-dominant triplets (issue 13, item 2): plane detection, plane + parallax, tensors."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.geometry.planarity import (
    PLANAR_SHARE,
    dominant_plane,
    plane_parallax_cameras,
)
from colmap_trifocal.geometry.projective_ba import refine_triplet
from colmap_trifocal.geometry.tensor_estimation import (
    TensorEstimationOptions,
    estimate_triplet_tensor,
    transfer_errors,
)
from colmap_trifocal.geometry.trifocal import (
    intrinsics_matrix,
    normalize_tensor,
    tensor_from_cameras,
)
from colmap_trifocal.synthetic.database import scene_contents
from colmap_trifocal.synthetic.facade import facade_scene

THRESHOLD_PX = 4.0


def normalised_tracks(scene, views: tuple[int, int, int], K0: np.ndarray):
    """Tracks seen in all three views: pixels (3, n, 2) and prior-normalised (3, n, 2)."""
    seen = scene.visible[list(views)].all(axis=0)
    pixels = scene.observations[list(views)][:, seen]
    homogeneous = np.concatenate([pixels, np.ones(pixels.shape[:2] + (1,))], axis=2)
    return pixels, (homogeneous @ np.linalg.inv(K0).T)[..., :2]


def tensor_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance of two unit-norm tensors up to sign."""
    return float(min(np.linalg.norm(a - b), np.linalg.norm(a + b)))


@pytest.mark.parametrize("seed", [1, 3])
def test_facade_triplets_are_planar_and_general_scenes_are_not(seed: int) -> None:
    facade = facade_scene(relief=0.01, seed=seed, noise_px=1.0, outlier_ratio=0.05)
    general = facade_scene(relief=0.3, seed=seed, noise_px=1.0, outlier_ratio=0.05)
    K0 = intrinsics_matrix(facade.intrinsics)
    threshold = THRESHOLD_PX / K0[0, 0]
    for views in [(0, 1, 2), (3, 4, 5)]:
        planar = dominant_plane(normalised_tracks(facade, views, K0)[1], threshold)
        spread = dominant_plane(normalised_tracks(general, views, K0)[1], threshold)
        assert planar is not None and planar.planar, (views, planar and planar.share)
        assert spread is None or not spread.planar, (views, spread.share)


def test_plane_parallax_cameras_start_at_the_noise_free_geometry() -> None:
    """Without noise, plane + parallax explains the tracks to a few pixels (the plane's
    homographies absorb a little relief) and the BA from it reaches the exact tensor."""
    scene = facade_scene(relief=0.01, seed=3, noise_px=0.0, outlier_ratio=0.05)
    K0 = intrinsics_matrix(scene.intrinsics * 1.04)
    views = (0, 1, 2)
    _, x = normalised_tracks(scene, views, K0)
    threshold = THRESHOLD_PX / K0[0, 0]
    plane = dominant_plane(x, threshold)
    assert plane is not None and plane.planar
    cameras = plane_parallax_cameras(x, plane, threshold, np.random.default_rng(0))
    assert cameras is not None
    scale = np.array([K0[0, 0], K0[1, 1]])
    errors = np.sqrt(transfer_errors(x, *cameras, scale))
    outliers = scene.outliers_in(views)[scene.visible[list(views)].all(axis=0)]
    assert np.median(errors[~outliers]) < THRESHOLD_PX
    clean = ~outliers
    refined = refine_triplet(x[:, clean], *cameras, scale, max_iterations=200, tolerance=1e-12)
    tensor = normalize_tensor(tensor_from_cameras(refined.P2, refined.P3))
    assert tensor_distance(tensor, scene.true_tensor(views, K0)) < 1e-3


def test_planar_triplet_tensor_stays_near_the_true_one() -> None:
    """A 1 %-relief facade triplet whose tensor ended far away (0.84 in unit norm) before."""
    scene = facade_scene(relief=0.01, seed=0, noise_px=1.0, num_points=1000)
    K0 = intrinsics_matrix(scene.intrinsics * 1.03)
    views = (2, 3, 7)
    pixels, _ = normalised_tracks(scene, views, K0)
    planar = TensorEstimationOptions(planar_share=PLANAR_SHARE)
    tensor = estimate_triplet_tensor(views, pixels, K0, np.random.default_rng(0), planar)
    assert tensor is not None
    assert tensor_distance(tensor.tensor, scene.true_tensor(views, K0)) < 0.2


def test_general_triplets_are_estimated_as_before() -> None:
    """Switching the planar handling on leaves a triplet with depth spread untouched."""
    scene = facade_scene(relief=0.3, seed=2, noise_px=1.0, num_points=800)
    K0 = intrinsics_matrix(scene.intrinsics * 0.97)
    views = (0, 3, 6)
    pixels, _ = normalised_tracks(scene, views, K0)
    planar = TensorEstimationOptions(planar_share=PLANAR_SHARE)
    default = estimate_triplet_tensor(views, pixels, K0, np.random.default_rng(5), planar)
    off = estimate_triplet_tensor(views, pixels, K0, np.random.default_rng(5))
    assert default is not None and off is not None
    np.testing.assert_array_equal(default.tensor, off.tensor)
    assert tensor_distance(default.tensor, scene.true_tensor(views, K0)) < 0.05


def test_planar_option_makes_facade_triplets_agree() -> None:
    """Facade with 1 % relief, ±5 % prior: with the planar handling at least 15 of 20
    triplets agree (11 without it, measured); the estimate stays within 0.1 %."""
    scene = facade_scene(relief=0.01, seed=0, noise_px=1.0, num_points=1000)
    truth = scene.intrinsics
    prior = truth * (1.0 + 0.05 * np.random.default_rng(99).choice([-1.0, 1.0], 4))
    options = CalibrationOptions(
        prior=tuple(prior),
        seed=0,
        workers=1,
        tensor=TensorEstimationOptions(planar_share=PLANAR_SHARE),
    )
    (result,) = calibrate_contents(scene_contents(scene), options)
    assert result.num_triplets == 20
    assert result.num_inlier_triplets >= 15
    assert all(result.observable.values())
    assert np.abs(result.intrinsics / truth - 1.0).mean() < 0.001
