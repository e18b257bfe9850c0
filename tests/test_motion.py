"""Tests of the two-view motion (:mod:`colmap_trifocal.geometry.motion`); fast, no I/O."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colmap_trifocal.geometry.motion import recover_pose


def two_views(
    seed: int, n: int = 300, noise: float = 1e-3, outliers: float = 0.2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normalised matches (n, 2) of points 3–8 baselines in front of view 1, and the
    true motion (R, unit t) of view 2; ``outliers`` of the matches are random."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(0.0, 0.15, 3)).as_matrix()
    t = rng.normal(size=3)
    t /= np.linalg.norm(t)
    points = np.column_stack([rng.uniform(-2.0, 2.0, (n, 2)), rng.uniform(3.0, 8.0, n)])
    local = points @ R.T + t
    x1 = points[:, :2] / points[:, 2:] + rng.normal(0.0, noise, (n, 2))
    x2 = local[:, :2] / local[:, 2:] + rng.normal(0.0, noise, (n, 2))
    wrong = rng.random(n) < outliers
    x2[wrong] = rng.uniform(-0.5, 0.5, (int(wrong.sum()), 2))
    return x1, x2, R, t


@pytest.mark.parametrize("seed", range(6))
def test_recover_pose_is_opencvs_decomposition_and_finds_the_motion(seed: int) -> None:
    x1, x2, R, t = two_views(seed)
    E, mask = cv2.findEssentialMat(
        x1, x2, np.eye(3), method=cv2.USAC_DEFAULT, prob=0.999, threshold=3e-3
    )
    votes, R_found, t_found, voters = recover_pose(E, x1, x2, mask)
    cv_votes, cv_R, cv_t, cv_mask = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask.copy())
    # OpenCV's choice among the same four candidates, and its votes to within the
    # points whose depth sits at a bound.
    np.testing.assert_array_equal(R_found, cv_R)
    np.testing.assert_array_equal(t_found, cv_t.ravel())
    assert abs(votes - cv_votes) <= 0.01 * len(x1)
    assert np.count_nonzero(voters != (cv_mask.ravel() > 0)) <= 0.01 * len(x1)
    # The true motion, and only the essential matrix's inliers vote.
    assert np.degrees(Rotation.from_matrix(R_found @ R.T).magnitude()) < 0.5
    assert np.dot(t_found, t) > 0.999
    assert votes == np.count_nonzero(voters) > 0.7 * len(x1)
    assert not np.any(voters & (mask.ravel() == 0))


def test_recover_pose_prefers_the_decomposition_with_points_in_front() -> None:
    x1, x2, R, t = two_views(0, outliers=0.0)
    E = np.cross(t, R, axisa=0, axisb=0, axisc=0)  # [t]ₓ R
    votes, R_found, t_found, voters = recover_pose(E, x1, x2)
    assert votes == len(x1) and voters.all()
    np.testing.assert_allclose(R_found, R, atol=1e-9)
    np.testing.assert_allclose(t_found, t, atol=1e-9)
    # The same matches seen with the views swapped: the inverse motion.
    _, R_back, t_back, _ = recover_pose(E.T, x2, x1)
    np.testing.assert_allclose(R_back, R.T, atol=1e-9)
    np.testing.assert_allclose(t_back, -R.T @ t, atol=1e-9)
