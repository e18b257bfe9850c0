"""Tests of the robust per-triplet tensor estimation on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_trifocal.geometry import projective_ba
from colmap_trifocal.geometry.projective_ba import MIN_SIGMA_PX, refine_triplet, refined_cost
from colmap_trifocal.geometry.tensor_estimation import (
    TensorEstimationOptions,
    TripletTensor,
    transfer_errors,
)
from colmap_trifocal.geometry.trifocal import (
    cameras_from_tensor,
    intrinsics_matrix,
    linear_tensor,
    normalize_tensor,
    quartic_constraints,
    tensor_from_cameras,
)
from colmap_trifocal.geometry.triplet_fit import estimate_triplet_tensor, fit_triplet
from colmap_trifocal.synthetic.facade import facade_scene
from colmap_trifocal.synthetic.scenes import (
    SyntheticScene,
    make_scene,
    perturbed_prior,
    triplet_tensors,
)

VIEWS = (0, 1, 2)
UNIFORM_STD = 1.0 / np.sqrt(3.0)  # std of U(−1, 1)


def sign_free_error(A: np.ndarray, B: np.ndarray) -> float:
    """max |A − ±B| of two tensors."""
    return float(min(np.abs(A - B).max(), np.abs(A + B).max()))


def normalised_tracks(scene: SyntheticScene, K0: np.ndarray, views=VIEWS) -> np.ndarray:
    """Prior-normalised tracks ``K0⁻¹ x`` (3, n, 2) of ``views``."""
    x = scene.observations[list(views)]
    homogeneous = np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)
    return (homogeneous @ np.linalg.inv(K0).T)[..., :2]


def estimate(
    noise_px: float, outlier_ratio: float = 0.0, seed: int = 0, num_points: int = 500
) -> tuple[SyntheticScene, np.ndarray, TripletTensor | None]:
    """A 3-camera scene, its ±5 % prior K0 and the tensor estimated from all its tracks."""
    rng = np.random.default_rng(seed)
    scene = make_scene(num_points, 3, noise_px, outlier_ratio, seed=rng)
    K0 = intrinsics_matrix(perturbed_prior(scene.intrinsics, 0.05, rng))
    return scene, K0, estimate_triplet_tensor(VIEWS, scene.observations, K0, rng)


@pytest.fixture(scope="module")
def noise_free() -> tuple[SyntheticScene, np.ndarray, TripletTensor | None]:
    return estimate(0.0)


@pytest.fixture(scope="module")
def noisy() -> tuple[SyntheticScene, np.ndarray, TripletTensor | None]:
    return estimate(0.5, seed=1)


def test_synthetic_tracks_are_consistent() -> None:
    """The true cameras reproject the noise-free tracks exactly (sanity of the harness)."""
    scene = make_scene(200, 3, seed=2)
    K0 = intrinsics_matrix(perturbed_prior(scene.intrinsics, 0.05, 3))
    P = scene.camera_matrices(np.linalg.solve(K0, scene.K))
    P = P @ np.linalg.inv(np.vstack([P[0], [0.0, 0.0, 0.0, 1.0]]))
    errors = transfer_errors(normalised_tracks(scene, K0), P[1], P[2], K0[[0, 1], [0, 1]])
    assert errors.shape == (200,)
    assert np.sqrt(errors.max()) < 1e-8
    T = scene.true_tensor(VIEWS, K0)
    assert sign_free_error(T, normalize_tensor(tensor_from_cameras(P[1], P[2]))) < 1e-14
    # With the true K the tensor is calibrated.
    assert np.abs(quartic_constraints(scene.true_tensor(VIEWS))).max() < 1e-12


def test_noise_free_tensor_is_exact(noise_free) -> None:
    scene, K0, result = noise_free
    assert result is not None
    assert result.image_ids == VIEWS
    assert result.num_tracks == result.num_inliers == scene.num_points
    assert result.inliers.all()
    assert sign_free_error(result.tensor, scene.true_tensor(VIEWS, K0)) < 1e-6
    # Exact tracks: the noise is at its floor, a float32 keypoint's precision.
    assert result.sigma_px == MIN_SIGMA_PX
    # The tensor is that of the returned cameras, unit norm.
    assert np.linalg.norm(result.tensor) == pytest.approx(1.0)
    own = normalize_tensor(tensor_from_cameras(result.P2, result.P3))
    assert sign_free_error(result.tensor, own) < 1e-14
    assert result.camera_covariance.shape == (24, 24)


def test_noisy_sigma_matches_the_pixel_noise(noisy) -> None:
    """σ of the Gold Standard fit ≈ std of U(−0.5, 0.5) px = 0.29 px, within 30 %."""
    scene, K0, result = noisy
    assert result is not None
    assert result.num_inliers >= 0.98 * scene.num_points
    assert result.sigma_px == pytest.approx(0.5 * UNIFORM_STD, rel=0.3)
    # Accurate to the level expected for 500 tracks at 0.3 px (measured ~4e-4).
    assert sign_free_error(result.tensor, scene.true_tensor(VIEWS, K0)) < 3e-3
    covariance = result.camera_covariance
    assert np.all(np.isfinite(covariance))
    np.testing.assert_allclose(covariance, covariance.T, atol=1e-12 * np.abs(covariance).max())
    assert np.linalg.eigvalsh(covariance).min() > -1e-9 * np.abs(covariance).max()


@pytest.mark.parametrize("seed", [0, 1])
def test_outlier_tracks_are_excluded(seed: int) -> None:
    """30 % of the tracks have one random observation: recall and precision > 95 %."""
    scene, _, result = estimate(0.5, outlier_ratio=0.3, seed=seed)
    assert result is not None
    clean = ~scene.outliers_in(VIEWS)
    assert np.count_nonzero(~clean) == 150
    true_positives = np.count_nonzero(result.inliers & clean)
    assert true_positives / np.count_nonzero(clean) > 0.95  # recall
    assert true_positives / np.count_nonzero(result.inliers) > 0.95  # precision
    assert result.sigma_px == pytest.approx(0.5 * UNIFORM_STD, rel=0.3)


def test_outliers_of_other_views_are_inliers_of_a_triplet() -> None:
    """In a 4-camera scene, a track corrupted in view 3 is clean for triplet (0, 1, 2)."""
    scene = make_scene(300, 4, 0.0, 0.3, seed=4)
    views = (0, 1, 2)
    assert np.array_equal(scene.outliers_in(views), np.isin(scene.outlier_views, views))
    assert np.count_nonzero(scene.outliers & ~scene.outliers_in(views)) > 0
    K0 = scene.K
    errors = transfer_errors(
        normalised_tracks(scene, K0, views), *_true_cameras(scene, K0, views), np.ones(2)
    )
    assert np.all(errors[~scene.outliers_in(views)] < 1e-16)


def _true_cameras(
    scene: SyntheticScene, K0: np.ndarray, views=VIEWS
) -> tuple[np.ndarray, np.ndarray]:
    """True P2, P3 in K0-normalised coordinates with P1 = [I|0]."""
    P = scene.camera_matrices(np.linalg.solve(K0, scene.K))[list(views)]
    P = P @ np.linalg.inv(np.vstack([P[0], [0.0, 0.0, 0.0, 1.0]]))
    return P[1], P[2]


def test_projective_ba_does_not_increase_the_cost(noisy) -> None:
    scene, K0, _ = noisy
    x = normalised_tracks(scene, K0)
    scale = K0[[0, 1], [0, 1]]
    # Start from the (inaccurate) linear tensor of 50 tracks.
    P2, P3 = cameras_from_tensor(linear_tensor(*x[:, :50]))
    start = refine_triplet(x, P2, P3, scale, max_iterations=0)
    refined = refine_triplet(x, P2, P3, scale)
    assert refined.squared_errors.sum() <= start.squared_errors.sum()
    # It reaches (at least) the cost of the true cameras and a noise estimate of 0.29 px.
    P2_true, P3_true = _true_cameras(scene, K0)
    at_truth = refine_triplet(x, P2_true, P3_true, scale, max_iterations=0)
    assert refined.squared_errors.sum() <= at_truth.squared_errors.sum() * (1 + 1e-9)
    assert refined.sigma == pytest.approx(0.5 * UNIFORM_STD, rel=0.3)
    # Refining an optimum again does not move the cost.
    again = refine_triplet(x, refined.P2, refined.P3, scale, points=refined.points)
    assert again.squared_errors.sum() <= refined.squared_errors.sum() * (1 + 1e-12)


def test_refined_cost_is_the_refinements_cost_and_sigma(noisy) -> None:
    """The polish's projective reference: the same LM, without the covariance."""
    scene, K0, _ = noisy
    x = normalised_tracks(scene, K0)
    scale = K0[[0, 1], [0, 1]]
    P2, P3 = cameras_from_tensor(linear_tensor(*x[:, :50]))
    full = refine_triplet(x, P2, P3, scale, max_iterations=20, tolerance=1e-9)
    squared_errors, sigma = refined_cost(x, P2, P3, scale, max_iterations=20, tolerance=1e-9)
    np.testing.assert_array_equal(squared_errors, full.squared_errors)
    assert sigma == full.sigma and full.iterations > 1


def test_too_few_tracks_give_none() -> None:
    scene = make_scene(20, 3, seed=5)
    K0 = scene.K
    rng = np.random.default_rng(0)
    assert estimate_triplet_tensor(VIEWS, scene.observations, K0, rng) is None
    options = TensorEstimationOptions(min_inliers=10)
    assert estimate_triplet_tensor(VIEWS, scene.observations, K0, rng, options) is not None


def test_seeded_estimation_is_deterministic() -> None:
    scene = make_scene(300, 3, noise_px=0.5, outlier_ratio=0.2, seed=6)
    K0 = intrinsics_matrix(perturbed_prior(scene.intrinsics, 0.05, 7))
    first = estimate_triplet_tensor(VIEWS, scene.observations, K0, np.random.default_rng(8))
    second = estimate_triplet_tensor(VIEWS, scene.observations, K0, np.random.default_rng(8))
    assert first is not None and second is not None
    np.testing.assert_array_equal(first.tensor, second.tensor)
    np.testing.assert_array_equal(first.camera_covariance, second.camera_covariance)
    np.testing.assert_array_equal(first.inliers, second.inliers)
    assert first.sigma_px == second.sigma_px


def test_synthetic_scene_is_seeded() -> None:
    a = make_scene(100, 4, noise_px=1.0, outlier_ratio=0.1, seed=9)
    b = make_scene(100, 4, noise_px=1.0, outlier_ratio=0.1, seed=np.random.default_rng(9))
    np.testing.assert_array_equal(a.observations, b.observations)
    np.testing.assert_array_equal(a.outlier_views, b.outlier_views)
    assert not np.array_equal(a.observations, make_scene(100, 4, 1.0, 0.1, seed=10).observations)


def test_synthetic_scene_geometry() -> None:
    scene = make_scene(400, 5, noise_px=0.5, outlier_ratio=0.25, seed=11)
    m, n = scene.num_cameras, scene.num_points
    assert scene.observations.shape == (m, n, 2)
    np.testing.assert_allclose(
        scene.rotations @ np.swapaxes(scene.rotations, 1, 2),
        np.broadcast_to(np.eye(3), (m, 3, 3)),
        atol=1e-12,
    )
    np.testing.assert_allclose(np.linalg.det(scene.rotations), 1.0)
    distances = np.linalg.norm(scene.centers, axis=1)
    assert np.all((distances > 5.4) & (distances < 6.6))
    # Cameras look roughly at the origin, but not all exactly (general position).
    to_origin = -scene.centers / distances[:, None]
    angles = np.rad2deg(np.arccos(np.clip((scene.rotations[:, 2] * to_origin).sum(1), -1, 1)))
    assert angles.max() <= 5.0 + 1e-9 and angles.min() > 0.0
    # Points in the cube; exact projections in the image, noise bounded by 0.5 px.
    assert np.abs(scene.points).max() <= 1.0
    exact = scene.project()
    assert np.all((exact >= 0) & (exact <= [scene.width, scene.height]))
    clean = ~scene.outliers
    assert np.abs(scene.observations[:, clean] - exact[:, clean]).max() <= 0.5
    assert scene.outliers.sum() == 100
    assert np.all(scene.outlier_views[scene.outliers] >= 0)
    assert np.all(scene.outlier_views[clean] == -1)


def test_triplet_tensors_cover_all_triplets() -> None:
    scene = make_scene(200, 4, noise_px=0.2, seed=12)
    prior = perturbed_prior(scene.intrinsics, 0.05, 13)
    tensors = triplet_tensors(scene, prior, 14)
    assert [t.image_ids for t in tensors] == [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]
    K0 = intrinsics_matrix(prior)
    for t in tensors:
        assert sign_free_error(t.tensor, scene.true_tensor(t.image_ids, K0)) < 3e-3


def _psi(X: np.ndarray, Y: np.ndarray) -> float:
    return float(np.trace(X) * np.trace(Y) - 2.0 * np.trace(X @ Y))


def test_quartic_constraints_match_their_written_form() -> None:
    """The 15 constraints (computed from one table of traces) equal the ψ formulas of
    the docstring evaluated matrix by matrix, on arbitrary (uncalibrated) tensors."""
    rng = np.random.default_rng(3)
    for T in rng.normal(size=(5, 3, 3, 3)):
        U = [T[k] @ T[k].T for k in range(3)]
        V = [T[k] @ T[(k + 1) % 3].T + T[(k + 1) % 3] @ T[k].T for k in range(3)]
        expected = []
        cycles = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
        for a, b, c in cycles:
            D = U[c] - U[a]
            expected += [
                _psi(D, D) - _psi(V[c], V[c]),
                _psi(D, V[a]) + _psi(V[b], V[c]),
                _psi(U[a] - U[b], V[a]),
            ]
        for a, b, c in cycles:
            D = U[c] - U[a]
            expected += [
                np.trace(U[b]) ** 2
                - np.trace(V[c]) ** 2
                - np.trace(U[b] @ U[b] - V[c] @ V[c] + D @ D),
                np.trace(V[b]) * np.trace(U[a] - 2 * U[b] - U[c])
                - np.trace(V[a]) * np.trace(V[c])
                + 2 * np.trace(V[b] @ U[b]),
            ]
        np.testing.assert_allclose(quartic_constraints(T), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("scene_name", "seed"), [("facade", 1), ("facade", 2), ("cube", 3)])
def test_second_start_completes_the_first_fit_exactly(scene_name: str, seed: int) -> None:
    """A fit from one start, completed with its deferred calibrated hypothesis, is the
    fit from both starts with the same seed (what lets the tensors stage refine only
    the start it adds). Starts 30 % long in f, as from COLMAP's default camera, where a
    linear hypothesis beats the calibrated one; a near-planar facade (on seed 1 the
    deferred start's refinement fails) and a general scene."""
    if scene_name == "facade":
        scene = facade_scene(relief=0.01, num_images=3, seed=seed, noise_px=1.0, num_points=1000)
    else:
        scene = make_scene(300, 3, 1.0, 0.1, seed=seed)
    K0 = intrinsics_matrix(scene.intrinsics * np.array([1.3, 1.3, 1.0, 1.0]))
    x = scene.observations[list(VIEWS)]
    first = fit_triplet(VIEWS, x, K0, np.random.default_rng(seed), second_start=False)
    both = fit_triplet(VIEWS, x, K0, np.random.default_rng(seed), second_start=True)
    assert first is not None and both is not None
    assert first.deferred is not None and both.deferred is None
    completed = first.with_second_start()
    assert completed.deferred is None
    assert [c[2] for c in completed.candidates] == [c[2] for c in both.candidates]
    assert completed.tensor is not None and both.tensor is not None
    np.testing.assert_array_equal(completed.tensor.tensor, both.tensor.tensor)
    np.testing.assert_array_equal(completed.tensor.inliers, both.tensor.inliers)
    assert completed.with_second_start() is completed


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_refinement_stops_where_gauss_newton_predicts_nothing_left(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a near-planar triplet (1 % relief) the relative cost decrease stays above the
    final tolerance after the optimum is reached: the refinement stops at the first
    Gauss–Newton step whose predicted decrease is below 1 % of σ², earlier than the
    relative rule, and the cost it ends at is that of full convergence to 1 % of σ²."""
    x, P2, P3, scale = _near_planar_triplet(seed, 1e-3)
    stopped = refine_triplet(x, P2, P3, scale, None, 300, 1e-9)
    monkeypatch.setattr(projective_ba, "DECREMENT_STOP", 0.0)
    full = refine_triplet(x, P2, P3, scale, None, 300, 1e-9)
    assert stopped.iterations < full.iterations
    gap = float(stopped.squared_errors.sum() - full.squared_errors.sum())
    assert 0.0 <= gap < 0.01 * full.sigma**2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_near_planar_triplet_converges_in_a_few_steps(seed: int) -> None:
    """Levenberg's damping on a near-planar triplet (1 % relief), from cameras 3 % off:
    the refinement reaches the fully converged cost (to 1 % of σ²) within 8 steps
    (Marquardt's diagonal scaling took 10-13 on the same starts)."""
    x, P2, P3, scale = _near_planar_triplet(seed, 3e-2)
    result = refine_triplet(x, P2, P3, scale, None, 300, 1e-9)
    assert result.iterations <= 8
    converged = refine_triplet(x, result.P2, result.P3, scale, result.points, 300, 0.0)
    gap = float(result.squared_errors.sum() - converged.squared_errors.sum())
    assert 0.0 <= gap < 0.01 * converged.sigma**2


def _near_planar_triplet(
    seed: int, perturbation: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(tracks normalised by a K0 5 % long, P2, P3, pixel scale) of a facade triplet with
    1 % relief, without outliers; the true cameras perturbed by ``perturbation`` of
    their norm."""
    scene = facade_scene(
        relief=0.01, num_images=3, seed=seed, noise_px=1.0, num_points=600, outlier_ratio=0.0
    )
    K0 = intrinsics_matrix(scene.intrinsics * np.array([1.05, 1.05, 1.0, 1.0]))
    assert scene.visible is not None
    seen = scene.visible[list(VIEWS)].all(axis=0)
    x = normalised_tracks(scene, K0)[:, seen]
    P = scene.camera_matrices(np.linalg.solve(K0, scene.K))
    P = P @ np.linalg.inv(np.vstack([P[0], [0.0, 0.0, 0.0, 1.0]]))
    rng = np.random.default_rng(seed)
    P2, P3 = (P[j] + perturbation * np.linalg.norm(P[j]) * rng.normal(size=(3, 4)) for j in (1, 2))
    return x, P2, P3, K0[[0, 1], [0, 1]]


def test_point_block_inverses_are_the_pseudo_inverses() -> None:
    """Cofactors where a block is well conditioned, SVD where it is singular: the
    pseudo-inverse either way (a point seen along its epipolar direction, a zero block)."""
    rng = np.random.default_rng(7)
    B = rng.normal(size=(40, 3, 3))
    V = B @ np.swapaxes(B, 1, 2)
    direction = rng.normal(size=(10, 3))
    V[:10] = np.einsum("ni,nj->nij", direction, direction)  # rank 1
    V[10] = 0.0
    expected = np.linalg.pinv(V)
    inverses = projective_ba.point_block_inverses(V)
    np.testing.assert_allclose(inverses, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(inverses[:11], expected[:11], rtol=0, atol=0)
