"""Which intrinsics the triplets determine: conditioning of the problem in K.

Some camera motions hide intrinsics from every self-calibration method:

* planar motion (all rotations about one axis, e.g. a car yawing on a road or
  an orbit at constant height): the focal length along that axis (fy for a
  level camera) is not determined;
* forward motion with little rotation: only a few combinations are;
* pure translation: nothing is (every K makes the tensors calibrated);
* too few or too short-baseline triplets: everything is weakly determined.

The test is the information about θ (the relative corrections of
:mod:`intrinsics.solve.constraints`) at the estimate: the curvature of the whitened
constraints combined with an image jackknife (:mod:`intrinsics.solve.uncertainty`), with
directions the raw constraints do not see at all removed (exact degeneracy,
where whitening by a tiny noise would hide it). For a :class:`.FreeParameters`
(``θ = A p + b``) the covariance is ``(Aᵀ H A)⁻¹``; directions whose information
is below ``MIN_EIGENVALUE_RATIO`` of the strongest count as null.

Each parameter's std is compared with its tolerance (:func:`tolerance`):
``MAX_RELATIVE_STD`` (1 %) of its scale, the focal length for fx and fy, half the
image size for cx and cy. Below 1 tolerance it is *observable*; up to
``FALLBACK_FACTOR`` (3) tolerances it is still estimated (jointly with the rest,
so it biases nothing) but reported as weakly determined; beyond that it is tied
(``fy = fx``) or held at the prior, whichever leaves the others determined
(:func:`select_free_parameters`). fx and fy are estimated apart only while both
stds are within the aspect ratio's own uncertainty (``TIED_ASPECT_STD``); a focal
length known worse than that is tied: square pixels are then the better evidence
(:func:`square_pixels_not_better`).

A tie or hold is judged with its own uncertainty counted (:func:`effective_std`):
an estimated parameter coupled to a held one would otherwise absorb the held
value's error unseen, with a conditional std far smaller than its error. The stds
these motions give, and the figures behind the constants: docs/uncertainty.md.
"""

from __future__ import annotations

import numpy as np

from .parametrization import (
    HELD,
    PARAMETER_NAMES,
    FreeParameters,
    Parametrization,
    candidate_free_parameters,
)

#: A parameter is observable when its std is below this fraction of its scale (the
#: focal length for fx, fy; half the image width / height for cx, cy).
MAX_RELATIVE_STD = 0.01
#: Beyond this many tolerances a parameter is tied or held instead of estimated.
FALLBACK_FACTOR = 3.0
#: Directions whose information is below this fraction of the largest count as null.
MIN_EIGENVALUE_RATIO = 1e-8
#: How well held values are known, relative to the focal length, when judging what
#: the estimated parameters inherit from them: a focal length prior is often 30 %
#: off (COLMAP's default, 1.2 · max(width, height), is a guess), a principal point
#: prior (the image centre) rarely more than 10 % of the focal length.
HELD_FOCAL_STD = 0.30
HELD_PRINCIPAL_POINT_STD = 0.10
#: How well ``fy = fx`` holds (aspect ratio, relative): square pixels within 1 %.
TIED_ASPECT_STD = 0.01


def conditioned_covariance(
    information: np.ndarray, parametrization: Parametrization
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (4, 4) of θ ``A (Aᵀ H A)⁻¹ Aᵀ`` without the null directions of ``Aᵀ H A``.

    Returns:
        The covariance (zero for held parameters and along null directions) and a
        (4,) mask of the θ that depend on an unknown with a component along a null
        (or non-positive) direction: those are undetermined.
    """
    matrix = parametrization.matrix
    if parametrization.dimension == 0:
        return np.zeros((4, 4)), np.zeros(4, dtype=bool)
    reduced = matrix.T @ information @ matrix
    eigenvalues, eigenvectors = np.linalg.eigh(0.5 * (reduced + reduced.T))
    largest = max(float(eigenvalues[-1]), 0.0)
    null = eigenvalues <= MIN_EIGENVALUE_RATIO * largest
    if largest <= 0.0:
        null[:] = True
    kept = eigenvectors[:, ~null]
    covariance = parametrization.covariance((kept / eigenvalues[~null]) @ kept.T)
    undetermined_free = (eigenvectors[:, null] ** 2).sum(axis=1) > 1e-6
    undetermined = (np.abs(matrix[:, undetermined_free]) > 0).any(axis=1)
    return covariance, undetermined


def relative_std(information: np.ndarray, parametrization: Parametrization) -> np.ndarray:
    """Std (4,) of θ under a parametrization: relative to the focal length.

    0 for held parameters, ``inf`` for undetermined ones (:func:`conditioned_covariance`).
    """
    covariance, undetermined = conditioned_covariance(information, parametrization)
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    std[undetermined] = np.inf
    return std


def default_held_std() -> np.ndarray:
    """How well held values from a prior are known (4,), relative to the focal length."""
    return np.array(
        [HELD_FOCAL_STD, HELD_FOCAL_STD, HELD_PRINCIPAL_POINT_STD, HELD_PRINCIPAL_POINT_STD]
    )


def constraint_information(
    free_parameters: FreeParameters,
    base: FreeParameters,
    start: np.ndarray,
    held_std: np.ndarray | None = None,
) -> np.ndarray:
    """Information P (4, 4) about θ of the ties and holds ``free_parameters`` adds to
    ``base``.

    A held value is known to ``held_std`` (θ units: relative to the focal length;
    default :func:`default_held_std`, ``HELD_FOCAL_STD`` for a focal length and
    ``HELD_PRINCIPAL_POINT_STD`` for a principal point coordinate), a tie
    ``fy = fx`` to ``TIED_ASPECT_STD`` in the aspect ratio (``d = (fy0/fx0)(−1, 1, 0, 0)``
    is its gradient in θ).
    """
    held_std = default_held_std() if held_std is None else np.asarray(held_std, float)
    information = np.zeros((4, 4))
    unit = np.eye(4)
    if free_parameters.focal == "held" and base.focal != "held":
        for index in (0, 1):
            information += np.outer(unit[index], unit[index]) / held_std[index] ** 2
    elif free_parameters.focal == "tied" and base.focal == "free":
        aspect = start[1] / start[0]
        gradient = aspect * np.array([-1.0, 1.0, 0.0, 0.0])
        information += np.outer(gradient, gradient) / TIED_ASPECT_STD**2
    for index, kept, base_kept in (
        (2, free_parameters.cx, base.cx),
        (3, free_parameters.cy, base.cy),
    ):
        if base_kept and not kept:
            information += np.outer(unit[index], unit[index]) / held_std[index] ** 2
    return information


def effective_std(
    information: np.ndarray,
    free_parameters: FreeParameters,
    base: FreeParameters,
    start: np.ndarray,
    held: np.ndarray,
    held_std: np.ndarray | None = None,
) -> np.ndarray:
    """Std (4,) of θ under ``free_parameters``, its ties and holds counted as
    uncertain, not exact.

    ``(H + P)⁻¹`` over ``base``'s unknowns, P from :func:`constraint_information`:
    an estimated parameter coupled to a held one inherits the held value's
    uncertainty instead of hiding it (estimating cy with fx held 5 % off, say).
    """
    constrained = information + constraint_information(free_parameters, base, start, held_std)
    return relative_std(constrained, base.parametrization(start, held))


def tolerance(start: np.ndarray, width: int, height: int) -> np.ndarray:
    """Largest std (4,) of θ at which each parameter counts as determined.

    ``MAX_RELATIVE_STD`` of the parameter's own scale: the focal length for fx and
    fy, half the image size for cx and cy (not the prior's principal point, which
    may be wrong), expressed in θ units (divided by fx0, fy0, fx0, fy0).
    """
    fx0, fy0 = float(start[0]), float(start[1])
    return MAX_RELATIVE_STD * np.array([1.0, 1.0, 0.5 * width / fx0, 0.5 * height / fy0])


def worst_estimated_std(
    std: np.ndarray, tolerances: np.ndarray, free_parameters: FreeParameters, *, single_focal: bool
) -> float:
    """Largest ``std / tolerance`` among the parameters ``free_parameters`` estimates
    (0 if none)."""
    estimated = free_parameters.estimated(single_focal=single_focal)
    ratios = np.asarray(std) / tolerances
    values = [r for r, name in zip(ratios, PARAMETER_NAMES, strict=True) if estimated[name]]
    return float(max(values, default=0.0))


def square_pixels_not_better(
    std: np.ndarray, free_parameters: FreeParameters, base: FreeParameters
) -> bool:
    """Whether estimating fx and fy apart beats assuming square pixels.

    A focal length the triplets know less well than the aspect ratio is known
    (``TIED_ASPECT_STD``) is better tied: ``fy = fx`` is then the stronger
    evidence, and an fy estimated from the little the motion says about it
    (planar motion with some pitch, e.g. a car's) would be further off than the
    tie. True when ``free_parameters`` or ``base`` has no free focal pair.

    Args:
        std: (4,) std of θ under ``free_parameters`` (relative to the focal length).
    """
    if free_parameters.focal != "free" or base.focal != "free":
        return True
    return bool(np.all(np.asarray(std)[:2] <= TIED_ASPECT_STD))


def select_free_parameters(
    information: np.ndarray,
    current: FreeParameters,
    base: FreeParameters,
    start: np.ndarray,
    held: np.ndarray,
    tolerances: np.ndarray,
    held_std: np.ndarray | None = None,
) -> FreeParameters:
    """The largest subset of ``current`` whose parameters are all within
    ``FALLBACK_FACTOR`` tolerances (a free fx, fy pair: within the aspect ratio's
    own uncertainty, :func:`square_pixels_not_better`).

    Args:
        information: H (4, 4) about θ at the current estimate, over ``base``'s unknowns.
        current: the parameters solved for last (the search only removes parameters).
        base: the most the camera model allows (all four, or one focal length).
        start: (fx0, fy0, cx0, cy0) the tensors were normalised with, pixels.
        held: values that held parameters keep (the prior), pixels.
        tolerances: (4,) the std of θ each parameter must stay below (:func:`tolerance`).
        held_std: (4,) how well the held values are known, θ units (None: a prior's).

    Returns:
        ``current`` when it qualifies; otherwise the fallback (at worst
        :data:`intrinsics.solve.parametrization.HELD`: everything held at the prior).
    """
    single_focal = base.focal == "tied"
    best: tuple[int, float, FreeParameters] | None = None
    for candidate in candidate_free_parameters(current):
        if best is not None and candidate.dimension < best[0]:
            break
        std = effective_std(information, candidate, base, start, held, held_std)
        worst = worst_estimated_std(std, tolerances, candidate, single_focal=single_focal)
        if worst >= FALLBACK_FACTOR or not square_pixels_not_better(std, candidate, base):
            continue
        if best is None or worst < best[1]:
            best = (candidate.dimension, worst, candidate)
    return HELD if best is None else best[2]
