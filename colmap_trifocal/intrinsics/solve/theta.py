"""Intrinsics as pixels, as relative corrections θ to a start, and as a matrix.

(fx, fy, cx, cy) in pixels, COLMAP's pixel convention; the start (fx0, fy0, cx0, cy0)
normalises the tensors' coordinates (``x̂ = K0⁻¹ x``); the unknowns are
``θ = (fx/fx0 − 1, fy/fy0 − 1, (cx − cx0)/fx0, (cy − cy0)/fy0)`` and a candidate acts
on normalised tensors through ``M(θ) = K0⁻¹ K``. K itself is
:func:`colmap_trifocal.geometry.trifocal.intrinsics_matrix`.
"""

from __future__ import annotations

import numpy as np


def theta_to_matrix(theta: np.ndarray) -> np.ndarray:
    """``M = K0⁻¹ K`` (..., 3, 3) from relative corrections θ (..., 4)."""
    M = np.zeros(theta.shape[:-1] + (3, 3))
    M[..., 0, 0] = 1.0 + theta[..., 0]
    M[..., 1, 1] = 1.0 + theta[..., 1]
    M[..., 0, 2] = theta[..., 2]
    M[..., 1, 2] = theta[..., 3]
    M[..., 2, 2] = 1.0
    return M


def theta_to_intrinsics(theta: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(fx, fy, cx, cy) in pixels from θ and the prior (fx0, fy0, cx0, cy0)."""
    fx0, fy0, cx0, cy0 = prior
    return np.array(
        [fx0 * (1 + theta[0]), fy0 * (1 + theta[1]), cx0 + fx0 * theta[2], cy0 + fy0 * theta[3]]
    )


def focal_scale(intrinsics: np.ndarray) -> np.ndarray:
    """(4,) what θ and relative std are relative to: (fx, fy, fx, fy) of ``intrinsics``
    (fx, fy, cx, cy), pixels. A principal point coordinate is relative to the focal
    length of its axis."""
    return np.array([intrinsics[0], intrinsics[1], intrinsics[0], intrinsics[1]], dtype=float)


def fold_focal_sign(intrinsics: np.ndarray) -> np.ndarray:
    """(fx, fy, cx, cy) with positive focal lengths (pixels).

    The 15 constraints cannot tell fx from −fx (nor fy from −fy): calibrating with
    ``K·diag(±1, ±1, 1)`` maps a calibrated tensor to the calibrated tensor of the
    mirrored cameras (``D R D`` is a rotation), and the constraint values are equal
    for any tensor (checked in ``tests/test_trifocal.py``). A solve that crossed
    zero therefore found the same K; this returns it with the physical sign.
    """
    folded = np.array(intrinsics, dtype=float)
    folded[..., :2] = np.abs(folded[..., :2])
    return folded


def intrinsics_to_theta(intrinsics: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Inverse of :func:`theta_to_intrinsics`."""
    fx0, fy0, cx0, cy0 = prior
    fx, fy, cx, cy = intrinsics
    return np.array([fx / fx0 - 1, fy / fy0 - 1, (cx - cx0) / fx0, (cy - cy0) / fy0])


def with_focal(intrinsics: np.ndarray, focal: float) -> np.ndarray:
    """(fx, fy, cx, cy) with √(fx·fy) set to ``focal`` (pixels), the aspect ratio and the
    principal point of ``intrinsics`` kept."""
    aspect = np.sqrt(intrinsics[1] / intrinsics[0])
    return np.array([focal / aspect, focal * aspect, intrinsics[2], intrinsics[3]])
