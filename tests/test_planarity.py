"""Planar-dominant triplets (issue 13, item 2): plane detection, plane + parallax, tensors."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import CliResult, small_texture_views

from colmap_trifocal import CalibrationOptions, calibrate_contents
from colmap_trifocal.database.features import build_database
from colmap_trifocal.geometry.parallax import plane_parallax, triplet_points
from colmap_trifocal.geometry.planarity import (
    PLANAR_SHARE,
    dominant_plane,
    plane_parallax_cameras,
)
from colmap_trifocal.geometry.projective_ba import refine_triplet
from colmap_trifocal.geometry.tensor_estimation import TensorEstimationOptions, transfer_errors
from colmap_trifocal.geometry.tracks import MatchGraph, select_triplets
from colmap_trifocal.geometry.trifocal import (
    intrinsics_matrix,
    normalize_tensor,
    tensor_from_cameras,
)
from colmap_trifocal.geometry.triplet_fit import estimate_triplet_tensor
from colmap_trifocal.intrinsics.solve.constraints import MSAC_TAU, ConstraintProblem
from colmap_trifocal.intrinsics.solve.theta import intrinsics_to_theta
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


@pytest.mark.parametrize("views", [(1, 3, 7), (4, 7, 9)])
def test_facade_triplet_tensor_agrees_with_the_true_intrinsics(views: tuple[int, int, int]) -> None:
    """1 % relief, +3 % prior: refined from two starts to convergence, the tensor's
    constraints at the true K are within the MSAC threshold. Measured with one start
    and the BA's usual stop (``final_ba_tolerance=1e-4, calibrated_start=False``):
    (1, 3, 7) ended in a local minimum (σ 0.78 px, ‖r‖ 514), (4, 7, 9) along a flat
    valley (σ 0.57 px, ‖r‖ 282); now ‖r‖ 3.7 and 8.0."""
    scene = facade_scene(relief=0.01, seed=0, noise_px=1.0, num_points=1000)
    prior = scene.intrinsics * 1.03
    K0 = intrinsics_matrix(prior)
    pixels, _ = normalised_tracks(scene, views, K0)
    tensor = estimate_triplet_tensor(views, pixels, K0, np.random.default_rng(0))
    assert tensor is not None
    theta = intrinsics_to_theta(scene.intrinsics, prior)
    assert ConstraintProblem.build([tensor], theta).norms(theta)[0] < MSAC_TAU
    assert tensor.sigma_px < 0.6  # uniform ±1 px noise: 0.577 px


def test_selection_prefers_wide_facade_triplets() -> None:
    """Ranked by tracks x parallax off the plane (keypoints given), the picked facade
    triplets span more of the walk than those ranked by tracks alone."""
    scene = facade_scene(relief=0.01, seed=0, noise_px=1.0, num_points=1000)
    contents = scene_contents(scene)
    graph = MatchGraph(contents.matches, {i: len(k) for i, k in contents.keypoints.items()})
    ids = sorted(contents.keypoints)
    by_tracks = select_triplets(graph, ids, 40, 20)
    by_parallax = select_triplets(graph, ids, 40, 20, keypoints=contents.keypoints)
    assert len(by_parallax) == 20

    def spans(triplets: list) -> np.ndarray:
        return np.array([t.image_ids[2] - t.image_ids[0] for t in triplets])

    assert np.median(spans(by_parallax)) >= np.median(spans(by_tracks)) + 2
    widest = max(by_parallax, key=lambda t: t.image_ids[2] - t.image_ids[0])
    assert plane_parallax(triplet_points(widest, contents.keypoints)) > 5.0


def test_facade_triplets_agree_and_the_estimate_is_accurate_by_default() -> None:
    """Facade with 1 % relief, ±5 % prior, default options: at least 15 of 20 triplets
    agree and the mean error of (fx, fy, cx, cy) is within 0.08 % (twice the 0.04 %
    of the same cameras on a scene spread through depth). Measured: 18/20, 0.05 %;
    before (tracks-only selection, one start, BA stopped at 1e-4): 12/20, 0.09 %."""
    scene = facade_scene(relief=0.01, seed=0, noise_px=1.0, num_points=1000)
    truth = scene.intrinsics
    prior = truth * (1.0 + 0.05 * np.random.default_rng(99).choice([-1.0, 1.0], 4))
    options = CalibrationOptions(prior=tuple(prior), seed=0, workers=1)
    (result,) = calibrate_contents(scene_contents(scene), options)
    assert result.num_triplets == 20
    assert result.num_inlier_triplets >= 15
    assert np.abs(result.intrinsics / truth - 1.0).mean() < 0.0008
    assert all(result.observable.values())


def test_small_views_of_a_plane_moved_sideways_hold_the_prior(
    tmp_path: Path, run_main: Callable[..., CliResult]
) -> None:
    """Six 100 x 75 views of a plane moved sideways determine nothing: ``calibrate``
    holds the prior and says so. Its triplets' refinement takes steps that lower the cost
    where almost no decrease was predicted; the damping update of such a step must stay
    finite (before, the cube of their gain ratio overflowed on seeds 0, 3 and 4)."""
    images = tmp_path / "images"
    images.mkdir()
    for k, view in enumerate(small_texture_views(7)[1:]):
        cv2.imwrite(str(images / f"{k}.png"), view)
    database = build_database(
        images, tmp_path / "db.db", camera_model="SIMPLE_RADIAL", camera_mode="single", seed=0
    )
    for seed in (0, 3, 4):
        result = run_main("calibrate", database, "--seed", seed, "--json", "-")
        assert result.returncode == 0, result.stderr
        assert "not determined by these images" in result.stderr
        [camera] = json.loads(result.stdout)
        assert camera["assumptions"] == ["fx, fy held at the prior", "cx, cy held at the prior"]
        # COLMAP's guess: f = 1.2 · 100 px, centred
        assert [camera[key] for key in ("fx", "fy", "cx", "cy")] == [120.0, 120.0, 50.0, 37.5]
        # What the images alone say of each value: undetermined, far above 10 % of f (a
        # held value's own solve has std 0, which the warning once quoted).
        assert all(std is None or std > 12.0 for std in camera["unconstrained_std"].values())
        assert "(std 0 px)" not in result.stderr
