"""Uncertainty of the intrinsics: curvature of the cost and an image jackknife.

Two estimates of the covariance of θ (the relative corrections of
:mod:`intrinsics.solve.constraints`):

* **Curvature**: ``H⁻¹`` with ``H = JᵀJ`` of the whitened constraints of the
  inlier tensors (:meth:`.ConstraintProblem.information`). Exact when the
  tensors are independent (one triplet, the paper's synthetic experiment). But
  triplets of a sequence share images and tracks, so their errors are correlated
  and H over-counts: the std alone is too small there.
* **Jackknife over images**: the images of the triplets are put into at most
  ``MAX_GROUPS`` groups (consecutive blocks on a sequence, :func:`image_groups`); each
  replicate drops one group's images (every tensor that uses one of them) and
  re-solves from the estimate (the method's local cost: least squares for ``direct``,
  a few rounds of the MSAC reweighting otherwise);
  ``C_J = (g − 1)/g Σ (θ_(i) − θ̄)(θ_(i) − θ̄)ᵀ``. Dropping whole images keeps the
  correlated tensors together.
  Each replicate is one Gauss–Newton step from the full estimate with the fit's
  weights (:func:`one_step_replicate`, the linearised jackknife), a small fraction of
  the cost of re-solving. It errs on the safe side: each replicate drops about 3/g of
  the tensors, not the 1/g the formula assumes. It also sees what the curvature
  misses, such as a focal length that varies with the images left out on forward
  motion. Coverage of both: docs/uncertainty.md.

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


def image_groups(
    image_ids: Sequence[tuple[int, ...]], max_groups: int = MAX_GROUPS
) -> list[set[int]]:
    """Images of the tensors in at most ``max_groups`` groups, in image id order:
    contiguous blocks where the triplets form a sequence (:func:`is_sequence`), else
    dealt round-robin.

    Why blocks on a sequence. Neighbouring frames of a drive or a video carry nearly the
    same information, so a round-robin group (every g-th frame) leaves every stretch of
    the sequence in each replicate: the replicates agree and the jackknife misses how
    much the estimate rests on one stretch (the turn of a drive). Deleting a block of
    consecutive frames is the block jackknife of dependent data. Images taken in no
    order (an object capture's) have no stretches: any grouping serves, and round-robin
    is kept.
    """
    images = sorted({i for ids in image_ids for i in ids})
    count = min(max_groups, len(images))
    if is_sequence(image_ids):
        n = len(images)
        return [set(images[g * n // count : (g + 1) * n // count]) for g in range(count)]
    return [set(images[g::count]) for g in range(count)]


def is_sequence(image_ids: Sequence[tuple[int, ...]]) -> bool:
    """Whether the triplets form a sequence: each lies within a window of at most half
    the images (by image id order, COLMAP's default being the file names' order), as
    triplets chosen from consecutive frames do. A ring whose triplets close the loop,
    or images matched in no order, span more."""
    images = sorted({i for ids in image_ids for i in ids})
    rank = {image: position for position, image in enumerate(images)}
    spans = [max(rank[i] for i in ids) - min(rank[i] for i in ids) for ids in image_ids]
    return bool(spans) and max(spans) <= len(images) // 2


def jackknife_replicates(
    image_ids: Sequence[tuple[int, ...]],
    replicate: Callable[[np.ndarray], np.ndarray | None],
    max_groups: int = MAX_GROUPS,
) -> np.ndarray | None:
    """θ of each delete-one-group replicate (g, 4), or None if fewer than MIN_GROUPS.

    Args:
        image_ids: per tensor, its image ids.
        replicate: the estimate from the tensors of a boolean mask (n,); None if none.
        max_groups: groups at most.
    """
    groups = image_groups(image_ids, max_groups)
    replicates = []
    for group in groups:
        keep = np.array([not (set(ids) & group) for ids in image_ids])
        if not keep.any():
            return None
        theta = replicate(keep)
        if theta is None or not np.all(np.isfinite(theta)):
            return None
        replicates.append(theta)
    if len(replicates) < MIN_GROUPS:
        return None
    return np.array(replicates)


def one_step_replicate(
    theta: np.ndarray,
    matrix: np.ndarray,
    residuals: np.ndarray,
    jacobians: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray | None:
    """θ of a replicate: one Gauss–Newton step from the full estimate on a subset.

    At the weighted least-squares optimum over all tensors the replicate without
    some of them is, to first order, ``θ + A Δp`` with ``Δp = −H⁻¹ g``,
    ``H = Σ w_i A_iᵀ A_i`` and ``g = Σ w_i A_iᵀ r_i`` over the kept tensors
    (``A_i = J_i A``). None when the kept tensors do not determine p.

    Args:
        theta: the full estimate (4,).
        matrix: A (4, k) of the estimate's parametrization.
        residuals: (m, 7) whitened residuals of the kept tensors at θ.
        jacobians: (m, 7, 4) their derivatives by θ.
        weights: (m,) the fit's weights of the kept tensors.
    """
    k = matrix.shape[1]
    if k == 0:
        return theta.copy()
    reduced = jacobians @ matrix  # (m, 7, k)
    hessian = np.einsum("m,mak,mal->kl", weights, reduced, reduced)
    gradient = np.einsum("m,mak,ma->k", weights, reduced, residuals)
    eigenvalues = np.linalg.eigvalsh(hessian)
    if eigenvalues[-1] <= 0.0 or eigenvalues[0] <= NULL_RATIO * eigenvalues[-1]:
        return None
    return np.asarray(theta - matrix @ np.linalg.solve(hessian, gradient))


def jackknife_covariance(replicates: np.ndarray) -> np.ndarray:
    """``(g − 1)/g Σ (θ_(i) − θ̄)(θ_(i) − θ̄)ᵀ`` of replicates (g, k)."""
    g = len(replicates)
    deviations = replicates - replicates.mean(axis=0)
    return np.asarray((g - 1) / g * deviations.T @ deviations)


def combined_information(
    curvature: np.ndarray, replicates: np.ndarray | None, parametrization: Parametrization
) -> np.ndarray:
    """Information (4, 4) about θ whose inverse is the larger covariance in every direction.

    Args:
        curvature: H (4, 4) about θ from the cost's curvature.
        replicates: jackknife θ (g, 4), or None (then H restricted to ``parametrization``).
        parametrization: the estimated unknowns ``θ = A p + b``.

    Returns:
        ``A⁺ᵀ H_p A⁺`` with ``H_p`` the combined information about p: zero outside
        the span of ``A``, so a subset of its unknowns ``A B`` gets ``Bᵀ H_p B``.
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
    return np.asarray(pseudo_inverse.T @ information_p @ pseudo_inverse)


def one_step_jackknife_std(
    intrinsics: np.ndarray,
    information: np.ndarray,
    gradients: np.ndarray,
    free: np.ndarray,
    groups: list[tuple[int, int, int]],
) -> np.ndarray | None:
    """(4,) delete-a-group-of-images jackknife std (pixels) of a shared camera: each
    replicate one Gauss–Newton step ``−(Σ_kept H_t)⁻¹ Σ_kept g_t`` from ``intrinsics``.

    ``information`` (m, 4, 4) and ``gradients`` (m, 4) per triplet, ``free`` (4, k) the
    refined parameters, ``groups`` the triplets' image ids. None with too few groups.
    """

    def replicate(keep: np.ndarray) -> np.ndarray | None:
        return gauss_newton_step(
            intrinsics, information[keep].sum(axis=0), gradients[keep].sum(axis=0), free
        )

    replicates = jackknife_replicates(groups, replicate)
    return None if replicates is None else np.sqrt(np.diag(jackknife_covariance(replicates)))


def restricted_information(information: np.ndarray, free: np.ndarray) -> np.ndarray | None:
    """``Aᵀ H A`` (k, k): a summed information H (q, q) on the k refined directions A
    (``free``, q × k); None where it is not finite or singular."""
    reduced = free.T @ information @ free
    if not np.all(np.isfinite(reduced)) or np.linalg.matrix_rank(reduced) < free.shape[1]:
        return None
    return np.asarray(reduced)


def gauss_newton_step(
    intrinsics: np.ndarray, information: np.ndarray, gradient: np.ndarray, free: np.ndarray
) -> np.ndarray | None:
    """The parameters after one Gauss–Newton step ``−A (AᵀHA)⁻¹ Aᵀg`` from ``intrinsics``
    on a summed information H (q, q) and gradient g (q,), along the refined directions
    A (``free``); None where :func:`restricted_information` is."""
    reduced = restricted_information(information, free)
    if reduced is None:
        return None
    return np.asarray(intrinsics - free @ np.linalg.solve(reduced, free.T @ gradient))
