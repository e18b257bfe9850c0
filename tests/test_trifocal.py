"""Tests of the trifocal tensor algebra (:mod:`colmap_trifocal.geometry.trifocal`); fast, no I/O."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_trifocal.geometry.trifocal import (
    NUM_CONSTRAINTS,
    calibrate_tensor,
    cameras_from_tensor,
    epipoles_from_tensor,
    intrinsics_matrix,
    linear_tensor,
    normalize_tensor,
    quartic_constraints,
    tensor_from_cameras,
    upper_triangular_inverse,
)

# Ground-truth intrinsics (fx, fy, cx, cy), pixels, of a 3072 x 2048 camera.
TRUE_INTRINSICS = np.array([2759.48, 2764.16, 1520.69, 1006.81])


def random_calibrated_cameras(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` pairs of calibrated cameras ``[R|t]`` (count, 3, 4) for views 2 and 3.

    Rotations are uniform (scipy), translations standard normal; view 1 is ``[I|0]``.
    """
    rng = np.random.default_rng(seed)
    R = Rotation.random(2 * count, random_state=seed).as_matrix().reshape(count, 2, 3, 3)
    t = rng.standard_normal((count, 2, 3, 1))
    return np.concatenate([R[:, 0], t[:, 0]], -1), np.concatenate([R[:, 1], t[:, 1]], -1)


def up_to_sign(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """max |A − ±B| per tensor of stacks (..., 3, 3, 3), the sign chosen per tensor."""
    axes = (-3, -2, -1)
    return np.minimum(np.abs(A - B).max(axis=axes), np.abs(A + B).max(axis=axes))


def pixel_tensors(P2: np.ndarray, P3: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Tensors of the pixel cameras ``K[I|0], K[R2|t2], K[R3|t3]``.

    The first camera is brought to ``[I|0]`` by ``H = diag(K⁻¹, 1)``, so the cameras
    are ``K[R|t] H = [K R K⁻¹ | K t]``.
    """
    H = np.eye(4)
    H[:3, :3] = np.linalg.inv(K)
    return tensor_from_cameras(K @ P2 @ H, K @ P3 @ H)


def project_scene(n: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Normalised projections (n, 2) in three views of points in front of all of them.

    Returns the three point sets and the true unit-norm tensor. Camera 1 is ``[I|0]``;
    cameras 2 and 3 are moderately rotated and translated so that all points (in a box
    4–6 units in front of camera 1) project within ±0.6 normalised units.
    """
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-1, 1, (n, 2)), rng.uniform(4, 6, n), np.ones(n)])
    rotvecs = rng.normal(scale=0.1, size=(2, 3))
    R = Rotation.from_rotvec(rotvecs).as_matrix()
    t = rng.normal(scale=0.5, size=(2, 3, 1))
    P2, P3 = (np.concatenate([R[i], t[i]], axis=1) for i in range(2))
    points = []
    for P in (np.eye(3, 4), P2, P3):
        y = X @ P.T
        points.append(y[:, :2] / y[:, 2:])
    return points, normalize_tensor(tensor_from_cameras(P2, P3))


def test_tensor_shape_and_normalisation() -> None:
    P2, P3 = random_calibrated_cameras(5)
    T = tensor_from_cameras(P2, P3)
    assert T.shape == (5, 3, 3, 3)
    norms = np.sqrt(np.einsum("nijk,nijk->n", *(normalize_tensor(T),) * 2))
    np.testing.assert_allclose(norms, 1.0, rtol=1e-14)


def test_tensor_slices_follow_hartley_zisserman() -> None:
    """``T_i = a_i b4ᵀ − a4 b_iᵀ`` for one pair of cameras, written out by hand."""
    P2, P3 = (P[0] for P in random_calibrated_cameras(1, seed=3))
    T = tensor_from_cameras(P2, P3)
    for i in range(3):
        expected = np.outer(P2[:, i], P3[:, 3]) - np.outer(P2[:, 3], P3[:, i])
        np.testing.assert_allclose(T[i], expected, atol=1e-15)


def test_constraints_vanish_on_calibrated_tensors() -> None:
    P2, P3 = random_calibrated_cameras(100)
    T = normalize_tensor(tensor_from_cameras(P2, P3))
    values = quartic_constraints(T)
    assert values.shape == (100, NUM_CONSTRAINTS)
    assert np.abs(values).max() < 1e-12
    # Transposing every slice (swapping the roles of views 2 and 3) keeps it calibrated.
    assert np.abs(quartic_constraints(np.swapaxes(T, -1, -2))).max() < 1e-12
    # Degree 4: independent of the sign.
    np.testing.assert_allclose(quartic_constraints(-T), values, atol=1e-15)


def test_constraints_are_homogeneous_of_degree_four() -> None:
    rng = np.random.default_rng(1)
    T = rng.standard_normal((3, 3, 3))
    np.testing.assert_allclose(
        quartic_constraints(2.0 * T), 16.0 * quartic_constraints(T), rtol=1e-12
    )


def test_constraints_do_not_vanish_on_generic_tensors() -> None:
    T = normalize_tensor(np.random.default_rng(2).standard_normal((50, 3, 3, 3)))
    assert np.all(np.linalg.norm(quartic_constraints(T), axis=-1) > 1e-3)


def test_calibrate_tensor_with_true_intrinsics() -> None:
    P2, P3 = random_calibrated_cameras(50, seed=4)
    K = intrinsics_matrix(TRUE_INTRINSICS)
    calibrated = calibrate_tensor(pixel_tensors(P2, P3, K), K)
    truth = normalize_tensor(tensor_from_cameras(P2, P3))
    assert up_to_sign(calibrated, truth).max() < 1e-12
    assert np.abs(quartic_constraints(calibrated)).max() < 1e-12


def test_calibrate_tensor_broadcasts_intrinsics() -> None:
    """One K per tensor (batch of K) gives the same as calibrating one at a time."""
    P2, P3 = random_calibrated_cameras(4, seed=5)
    K = intrinsics_matrix(TRUE_INTRINSICS * np.linspace(0.95, 1.05, 4)[:, None])
    T = pixel_tensors(P2, P3, intrinsics_matrix(TRUE_INTRINSICS))
    batched = calibrate_tensor(T, K)
    for i in range(4):
        np.testing.assert_allclose(batched[i], calibrate_tensor(T[i], K[i]), atol=1e-15)


def test_upper_triangular_inverse_is_the_inverse() -> None:
    """The closed form calibrate_tensor uses, on a batch with skew and a non-unit corner."""
    rng = np.random.default_rng(6)
    K = np.triu(rng.uniform(0.5, 2.0, size=(7, 3, 3))) * rng.choice([-1.0, 1.0], size=(7, 3, 3))
    np.testing.assert_allclose(upper_triangular_inverse(K), np.linalg.inv(K), rtol=1e-13)
    np.testing.assert_allclose(
        K @ upper_triangular_inverse(K), np.broadcast_to(np.eye(3), K.shape), atol=1e-13
    )


@pytest.mark.parametrize("parameter", [0, 1, 2, 3], ids=["fx", "fy", "cx", "cy"])
@pytest.mark.parametrize("fraction", [0.01, 0.05, -0.03])
def test_constraints_grow_with_wrong_intrinsics(parameter: int, fraction: float) -> None:
    """Calibrating a pixel tensor with one parameter off by 1–5 % breaks the constraints."""
    P2, P3 = random_calibrated_cameras(50, seed=6)
    K = intrinsics_matrix(TRUE_INTRINSICS)
    wrong = TRUE_INTRINSICS.copy()
    wrong[parameter] *= 1.0 + fraction
    values = quartic_constraints(
        calibrate_tensor(pixel_tensors(P2, P3, K), intrinsics_matrix(wrong))
    )
    assert np.linalg.norm(values, axis=-1).min() > 1e-4


def test_cameras_from_tensor_round_trip() -> None:
    P2, P3 = random_calibrated_cameras(50, seed=7)
    T = normalize_tensor(tensor_from_cameras(P2, P3))
    A, B = cameras_from_tensor(T)
    assert A.shape == B.shape == (50, 3, 4)
    assert up_to_sign(normalize_tensor(tensor_from_cameras(A, B)), T).max() < 1e-10


def test_cameras_from_tensor_round_trip_on_pixel_tensors() -> None:
    """Also for uncalibrated (projective) tensors of very different entry magnitudes."""
    P2, P3 = random_calibrated_cameras(20, seed=8)
    T = normalize_tensor(pixel_tensors(P2, P3, intrinsics_matrix(TRUE_INTRINSICS)))
    A, B = cameras_from_tensor(T)
    assert up_to_sign(normalize_tensor(tensor_from_cameras(A, B)), T).max() < 1e-9


def test_epipoles_are_images_of_the_first_centre() -> None:
    """e' ∝ P2 (0,0,0,1)ᵀ = a4 and e'' ∝ b4 for ``P1 = [I|0]``."""
    P2, P3 = random_calibrated_cameras(20, seed=9)
    e2, e3 = epipoles_from_tensor(tensor_from_cameras(P2, P3))
    for e, P in ((e2, P2), (e3, P3)):
        a4 = P[..., 3] / np.linalg.norm(P[..., 3], axis=-1, keepdims=True)
        assert np.minimum(np.abs(e - a4).max(-1), np.abs(e + a4).max(-1)).max() < 1e-12


@pytest.mark.parametrize("n", [7, 50])
def test_linear_tensor_is_exact_without_noise(n: int) -> None:
    points, truth = project_scene(n, seed=n)
    T = linear_tensor(*points)
    assert T.shape == (3, 3, 3)
    assert up_to_sign(T, truth) < 1e-8


def test_linear_tensor_is_batched() -> None:
    """Batch dimensions are solved at once and equal the one-at-a-time solutions."""
    rng = np.random.default_rng(10)
    points, truth = project_scene(60, seed=10)
    samples = np.stack([rng.choice(60, 9, replace=False) for _ in range(5)])
    batched = linear_tensor(*(p[samples] for p in points))
    assert batched.shape == (5, 3, 3, 3)
    for s, T in zip(samples, batched, strict=True):
        assert up_to_sign(T, linear_tensor(*(p[s] for p in points))) < 1e-10
    assert up_to_sign(batched, truth).max() < 1e-8


@pytest.mark.parametrize(
    "points",
    [
        np.tile([[0.1, -0.2]], (10, 1)),
        np.zeros((10, 2)),
        np.column_stack([np.linspace(-1, 1, 10), 0.5 * np.linspace(-1, 1, 10) + 0.1]),
    ],
    ids=["identical", "origin", "collinear"],
)
def test_linear_tensor_finite_on_degenerate_input(points: np.ndarray) -> None:
    """Degenerate samples give some unit-norm tensor (not NaN), and finite cameras."""
    T = linear_tensor(points, points, points)
    assert np.all(np.isfinite(T))
    assert np.linalg.norm(T) == pytest.approx(1.0)
    P2, P3 = cameras_from_tensor(T)
    assert np.all(np.isfinite(P2)) and np.all(np.isfinite(P3))


def test_intrinsics_matrix() -> None:
    K = intrinsics_matrix(TRUE_INTRINSICS)
    expected = np.array([[2759.48, 0.0, 1520.69], [0.0, 2764.16, 1006.81], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(K, expected)
    assert intrinsics_matrix(np.tile(TRUE_INTRINSICS, (2, 5, 1))).shape == (2, 5, 3, 3)


def _constraint_magnitudes(T: np.ndarray, params: np.ndarray) -> np.ndarray:
    """|constraints| of ``T`` calibrated by (fx, fy, cx, cy)."""
    calibrated = calibrate_tensor(T, intrinsics_matrix(params))
    return np.abs(quartic_constraints(normalize_tensor(calibrated)))


def test_constraints_cannot_tell_the_sign_of_a_focal_length() -> None:
    """fx → −fx or fy → −fy leaves every constraint value unchanged (any tensor, not only
    calibrated ones), so a solve that crosses zero found the same K:
    :func:`fold_focal_sign` returns it with positive focal lengths."""
    from colmap_trifocal.intrinsics.solve.theta import fold_focal_sign

    T = np.random.default_rng(0).standard_normal((3, 3, 3))
    params = np.array([700.0, 690.0, 600.0, 180.0])
    reference = _constraint_magnitudes(T, params)
    for signs in ([-1, 1], [1, -1], [-1, -1]):
        mirrored = params * np.array([*signs, 1, 1])
        np.testing.assert_allclose(_constraint_magnitudes(T, mirrored), reference, rtol=1e-9)
        np.testing.assert_array_equal(fold_focal_sign(mirrored), params)
    # A wrong K does change them (the test above is not vacuous).
    assert np.max(np.abs(_constraint_magnitudes(T, params * 1.1) - reference)) > 1e-4
