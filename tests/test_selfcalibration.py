"""Tests of the TrifocalCalib solvers (direct, msac, msac-opt) on synthetic scenes.

Each scene: 500 tracks, ±5 % prior on every parameter, tensors of all camera triplets
(:func:`colmap_trifocal.synthetic.scenes.triplet_tensors`). Tensors are cached per module.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from colmap_trifocal.geometry.tensor_estimation import TripletTensor
from colmap_trifocal.intrinsics.solve.constraints import (
    MSAC_TAU,
    ConstraintProblem,
    ConstraintSolution,
    msac_score,
    solve,
)
from colmap_trifocal.intrinsics.solve.parametrization import SINGLE_FOCAL
from colmap_trifocal.intrinsics.solve.theta import intrinsics_to_theta, theta_to_intrinsics
from colmap_trifocal.synthetic.scenes import make_scene, perturbed_prior, triplet_tensors

METHODS = ("direct", "msac", "msac-opt")
SEEDS = (0, 1, 2)


@cache
def scene_tensors(
    noise_px: float,
    num_cameras: int,
    outlier_ratio: float = 0.0,
    seed: int = 0,
    single_focal: bool = False,
) -> tuple[np.ndarray, np.ndarray, list[TripletTensor]]:
    """(true intrinsics, prior, tensors) of a seeded scene; cached across tests.

    For ``single_focal`` the camera has fx = fy and so has the prior (as the pipeline
    does: it averages the prior's focal lengths).
    """
    rng = np.random.default_rng(seed)
    intrinsics = np.array([2759.48, 2764.16, 1520.69, 1006.81])
    if single_focal:
        intrinsics[1] = intrinsics[0]
    scene = make_scene(500, num_cameras, noise_px, outlier_ratio, rng, intrinsics)
    prior = perturbed_prior(scene.intrinsics, 0.05, rng)
    if single_focal:
        prior[:2] = prior[:2].mean()
    return scene.intrinsics, prior, triplet_tensors(scene, prior, rng)


def relative_error(result: ConstraintSolution, truth: np.ndarray, prior: np.ndarray):
    """|estimate / truth − 1| per parameter (fx, fy, cx, cy)."""
    return np.abs(theta_to_intrinsics(result.theta, prior) / truth - 1.0)


def test_theta_round_trip() -> None:
    prior = np.array([2700.0, 2800.0, 1500.0, 1000.0])
    intrinsics = np.array([2759.48, 2764.16, 1520.69, 1006.81])
    theta = intrinsics_to_theta(intrinsics, prior)
    np.testing.assert_allclose(theta_to_intrinsics(theta, prior), intrinsics, rtol=1e-15)
    np.testing.assert_array_equal(intrinsics_to_theta(prior, prior), np.zeros(4))


@pytest.mark.parametrize(
    "method",
    [
        "direct",
        "msac",
        "msac-opt",
    ],
)
@pytest.mark.parametrize("seed", SEEDS[:2])
def test_exact_recovery_without_noise(method: str, seed: int) -> None:
    truth, prior, tensors = scene_tensors(0.0, 3, seed=seed)
    assert len(tensors) == 1
    assert np.abs(prior / truth - 1).max() > 0.01  # the prior is really off
    error = relative_error(solve(tensors, method), truth, prior)
    assert error.max() < 1e-4, error


@pytest.mark.parametrize("method", METHODS)
def test_noisy_accuracy(method: str) -> None:
    """0.5 px noise, 5 cameras (10 triplets): mean relative error < 1 % (measured ~0.04 %)."""
    errors = []
    for seed in SEEDS:
        truth, prior, tensors = scene_tensors(0.5, 5, seed=seed)
        assert len(tensors) == 10
        errors.append(relative_error(solve(tensors, method), truth, prior))
    errors = np.array(errors)
    assert errors.mean() < 0.01, errors
    assert errors.max() < 0.01, errors


@pytest.mark.parametrize("method", ["msac", "msac-opt"])
def test_accuracy_with_outlier_tracks(method: str) -> None:
    """30 % of the tracks corrupted in one view: mean relative error still < 1 %."""
    errors = []
    for seed in SEEDS:
        truth, prior, tensors = scene_tensors(0.5, 5, outlier_ratio=0.3, seed=seed)
        assert len(tensors) >= 8
        errors.append(relative_error(solve(tensors, method), truth, prior))
    errors = np.array(errors)
    assert errors.mean() < 0.01, errors


def test_whitened_residuals_are_chi_square_at_the_truth() -> None:
    """At the true θ, ‖r_i‖² ≈ χ²(7): mean over all tensors near 7, all below τ."""
    norms = []
    for seed in SEEDS:
        truth, prior, tensors = scene_tensors(0.5, 5, seed=seed)
        theta = intrinsics_to_theta(truth, prior)
        norms.append(ConstraintProblem.build(tensors, theta).norms(theta))
    norms = np.concatenate(norms)
    assert 7.0 / 2 < np.mean(norms**2) < 7.0 * 2
    assert norms.max() < MSAC_TAU


def test_single_focal_returns_equal_focals() -> None:
    truth, prior, tensors = scene_tensors(0.5, 4, seed=3, single_focal=True)
    result = solve(tensors, "msac-opt", SINGLE_FOCAL.parametrization(prior, prior))
    estimate = theta_to_intrinsics(result.theta, prior)
    assert estimate[0] == estimate[1]
    assert result.theta[0] == result.theta[1]
    assert np.abs(estimate / truth - 1).mean() < 0.01
    # The covariance's fy row repeats the fx row.
    np.testing.assert_array_equal(result.covariance[1], result.covariance[0])
    assert result.per_tensor_theta is not None
    np.testing.assert_array_equal(result.per_tensor_theta[:, 0], result.per_tensor_theta[:, 1])


def test_per_tensor_candidates_and_scores() -> None:
    truth, prior, tensors = scene_tensors(0.5, 5, seed=0)
    result = solve(tensors, "msac")
    n = len(tensors)
    candidates, scores = result.per_tensor_theta, result.per_tensor_scores
    assert candidates is not None and scores is not None
    assert candidates.shape == (n, 4) and scores.shape == (n,)
    assert np.all(np.isfinite(candidates))
    assert np.all(np.isfinite(scores)) and np.all((scores >= 0) & (scores <= 1))
    # msac picks the best-scoring candidate; its score is the one reported.
    best = int(np.argmax(scores))
    np.testing.assert_array_equal(result.theta, candidates[best])
    assert result.score == pytest.approx(scores[best])
    assert result.score == pytest.approx(msac_score(result.norms))
    # Most candidates are near the truth.
    candidate_errors = np.abs(
        np.array([theta_to_intrinsics(c, prior) for c in candidates]) / truth - 1
    )
    assert np.median(candidate_errors.max(axis=1)) < 0.01


def test_result_diagnostics() -> None:
    truth, prior, tensors = scene_tensors(0.5, 5, seed=1)
    result = solve(tensors, "msac-opt")
    n = len(tensors)
    assert result.norms.shape == result.inlier_tensors.shape == (n,)
    np.testing.assert_array_equal(result.inlier_tensors, result.norms < MSAC_TAU)
    assert result.inlier_tensors.sum() >= n - 2
    assert 0.0 <= result.score <= 1.0
    covariance = result.covariance
    assert covariance.shape == (4, 4)
    np.testing.assert_allclose(covariance, covariance.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    # The error is of the order of the reported σ. Loose bound: with all triplets of 5
    # cameras the tensors share their tracks, which the covariance does not model;
    # measured over repeated noise, the actual std is ~2x the reported one.
    theta_truth = intrinsics_to_theta(truth, prior)
    z = (result.theta - theta_truth) / np.sqrt(np.diag(covariance))
    assert np.abs(z).max() < 10.0, z
