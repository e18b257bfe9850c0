"""Each tensor's constraints whitened by their covariance.

The raw constraint values of different triplets are not comparable: a short-baseline
triplet with few tracks has a noisy tensor and large constraint values at the true K, a
wide triplet tiny ones. Each tensor's 15 values are therefore whitened with their
covariance propagated from the covariance of the refined cameras
(:mod:`colmap_trifocal.geometry.projective_ba`): ``Σ_c = J Σ_P Jᵀ`` with
``J = ∂c/∂vec(P2, P3)`` (central differences). Σ_c has rank 7, the codimension of
calibrated tensors among all tensors, and the whitened residual ``r = Λ^{-1/2} Vᵀ c``
(its top 7 eigenpairs) is, at the true K, approximately a standard normal 7-vector.
"""

from __future__ import annotations

import numpy as np

from ...geometry.tensor_estimation import TripletTensor
from ...geometry.trifocal import (
    CONSTRAINT_RANK,
    calibrate_tensor,
    normalize_tensor,
    quartic_constraints,
    tensor_from_cameras,
)
from .theta import theta_to_matrix

#: Central-difference step of the constraints' derivatives by the cameras' entries.
FD_STEP_CAMERA = 1e-6


def _constraints_of_cameras(P: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Constraints (..., 15) of the tensor of cameras P (..., 24) calibrated by M (3, 3)."""
    P2 = P[..., :12].reshape(P.shape[:-1] + (3, 4))
    P3 = P[..., 12:].reshape(P.shape[:-1] + (3, 4))
    return quartic_constraints(calibrate_tensor(normalize_tensor(tensor_from_cameras(P2, P3)), M))


def whitening_matrices(tensors: list[TripletTensor], theta: np.ndarray) -> np.ndarray:
    """Whitening matrices (n, 7, 15) of the constraints of each tensor, evaluated at θ.

    ``W_i = Λ^{-1/2} Vᵀ`` from the top-7 eigenpairs of ``Σ_c = J Σ_P Jᵀ``.
    """
    M = theta_to_matrix(np.asarray(theta, dtype=float))
    P = np.stack([np.concatenate([t.P2.ravel(), t.P3.ravel()]) for t in tensors])  # (n, 24)
    steps = FD_STEP_CAMERA * np.eye(24)
    plus = _constraints_of_cameras(P[:, None, :] + steps, M)  # (n, 24, 15)
    minus = _constraints_of_cameras(P[:, None, :] - steps, M)
    J = np.swapaxes(plus - minus, 1, 2) / (2 * FD_STEP_CAMERA)  # (n, 15, 24)
    covariance = np.stack([t.camera_covariance for t in tensors])
    sigma_c = J @ covariance @ np.swapaxes(J, 1, 2)
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (sigma_c + np.swapaxes(sigma_c, 1, 2)))
    top_values = np.maximum(eigenvalues[:, -CONSTRAINT_RANK:], 1e-300)
    top_vectors = eigenvectors[:, :, -CONSTRAINT_RANK:]
    return np.asarray(np.swapaxes(top_vectors, 1, 2) / np.sqrt(top_values)[:, :, None])
