"""Uncertainty of the intrinsics: curvature of the cost and an image jackknife.

Two estimates of the covariance of θ (the relative corrections of
:mod:`.selfcalibration`):

* **Curvature**: ``H⁻¹`` with ``H = JᵀJ`` of the whitened constraints of the
  inlier tensors (:meth:`.ConstraintProblem.information`). Exact when the
  tensors are independent; calibrated on the paper's synthetic experiment (one
  triplet). But triplets of a sequence share images and tracks, so their
  errors are correlated and H over-counts: measured on 8-image general-motion
  sequences (0.5 px, 20 triplets, 20 runs) the truth lay within ±2 std in only
  65–80 % of runs (rms of error/std 1.4–1.8).
* **Jackknife over images**: the images of the triplets are dealt into at most
  ``MAX_GROUPS`` groups; each replicate drops one group's images (every tensor
  that uses one of them) and re-solves from the estimate (the method's local
  cost: least squares for ``direct``, a few rounds of the MSAC reweighting
  otherwise); ``C_J = (g − 1)/g Σ (θ_(i) − θ̄)(θ_(i) − θ̄)ᵀ``. Dropping whole
  images keeps the correlated tensors together. Measured on the same sequences:
  85–95 % coverage (rms 1.0–1.2); on forward motion with no yaw it reveals a
  focal length varying by 1.4–3 % where the curvature said 0.2–0.8 %.

The reported covariance is the larger of the two in every direction: in the
coordinates where the curvature covariance is the identity, the jackknife
covariance's eigenvalues are raised to at least 1. Directions the curvature
says carry no information stay that way. The jackknife needs at least
``MIN_GROUPS`` groups whose removal leaves a tensor (4 images or more in the
triplets); otherwise the curvature alone is used (e.g. one triplet).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .parametrization import Parametrization

#: Image groups of the jackknife at most (replicates cost one local solve each).
MAX_GROUPS = 10
#: Fewer groups than this: no jackknife (its variance would rest on < 3 dof).
MIN_GROUPS = 4
#: Directions whose information is below this fraction of the largest are null.
NULL_RATIO = 1e-8


def image_groups(image_ids: Sequence[tuple[int, ...]], max_groups: int = MAX_GROUPS) -> list[set]:
    """Images of the tensors dealt into at most ``max_groups`` groups (sorted, round-robin)."""
    images = sorted({i for ids in image_ids for i in ids})
    count = min(max_groups, len(images))
    return [set(images[g::count]) for g in range(count)]


def jackknife_replicates(
    image_ids: Sequence[tuple[int, ...]],
    resolve: Callable[[np.ndarray], np.ndarray | None],
    max_groups: int = MAX_GROUPS,
) -> np.ndarray | None:
    """θ of each delete-one-group replicate (g, 4), or None if fewer than MIN_GROUPS.

    Args:
        image_ids: per tensor, its image ids.
        resolve: re-solves with the tensors of a boolean mask (n,); None when it cannot.
        max_groups: groups at most.
    """
    groups = image_groups(image_ids, max_groups)
    replicates = []
    for group in groups:
        keep = np.array([not (set(ids) & group) for ids in image_ids])
        if not keep.any():
            return None
        theta = resolve(keep)
        if theta is None or not np.all(np.isfinite(theta)):
            return None
        replicates.append(theta)
    if len(replicates) < MIN_GROUPS:
        return None
    return np.array(replicates)


def jackknife_covariance(replicates: np.ndarray) -> np.ndarray:
    """``(g − 1)/g Σ (θ_(i) − θ̄)(θ_(i) − θ̄)ᵀ`` of replicates (g, k)."""
    g = len(replicates)
    deviations = replicates - replicates.mean(axis=0)
    return (g - 1) / g * deviations.T @ deviations


def combined_information(
    curvature: np.ndarray, replicates: np.ndarray | None, parametrization: Parametrization
) -> np.ndarray:
    """Information (4, 4) about θ whose inverse is the larger covariance in every direction.

    Args:
        curvature: H (4, 4) about θ from the cost's curvature.
        replicates: jackknife θ (g, 4), or None (then H restricted to the model).
        parametrization: the estimated unknowns ``θ = A p + b``.

    Returns:
        ``A⁺ᵀ H_p A⁺`` with ``H_p`` the combined information about p: zero outside
        the model's span, so a sub-model ``A B`` gets ``Bᵀ H_p B``.
    """
    matrix = parametrization.matrix
    k = parametrization.dimension
    if k == 0:
        return np.zeros((4, 4))
    reduced = matrix.T @ curvature @ matrix
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (reduced + reduced.T))
    largest = max(float(eigenvalues[-1]), 0.0)
    informative = eigenvalues > NULL_RATIO * largest
    if largest <= 0.0 or not informative.any():
        return np.zeros((4, 4))
    # Whitening T (r, k): T C_curv Tᵀ = I on the informative directions.
    whitening = (eigenvectors[:, informative] * np.sqrt(eigenvalues[informative])).T
    information_p = whitening.T @ whitening
    if replicates is not None:
        free = parametrization.free(replicates)
        spread = whitening @ jackknife_covariance(free) @ whitening.T
        values, vectors = np.linalg.eigh(0.5 * (spread + spread.T))
        shrink = (vectors / np.maximum(values, 1.0)) @ vectors.T
        information_p = whitening.T @ shrink @ whitening
    pseudo_inverse = np.linalg.pinv(matrix)
    return pseudo_inverse.T @ information_p @ pseudo_inverse
