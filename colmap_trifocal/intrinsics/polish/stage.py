"""The polish stage: msac-opt's estimate replaced by the triplets' shared-camera bundle
adjustment (:mod:`intrinsics.polish.bundle`) where that is at least as well supported.

The bundle adjustment replaces the constraint estimate when

* at least as many triplets agree with it (λ < τ²) as tensors did (‖r‖ < τ), and
* its image jackknife variance is no larger than the constraint solve's where more
  triplets agree with it (the constraints' first-order whitening misjudged a
  near-planar triplet, which is what the polish is for), and at most
  ``VARIANCE_RATIO`` times the constraint solve's where as many agree. A variance
  here is the sum of the estimated parameters' jackknife variances relative to the
  focal length, over the same image groups (the polish's replicates are one
  Gauss–Newton step each on the triplets' Schur complements,
  :mod:`intrinsics.polish.information`). Two such variances from ten image groups differ by
  a factor of two by chance in about one case in five: without a triplet gained,
  the polish replaces the constraint estimate only on clear evidence that it is
  the tighter one.

Before any adjustment: where every tensor already agrees with the constraint
estimate (the polish cannot add triplets, and starts at its optimum's first-order
neighbourhood), its move and its jackknife are predicted from its first Gauss–Newton
step (:func:`intrinsics.polish.bundle.predict_polish`, milliseconds). It is not run where it
could not be kept (the predicted jackknife variance exceeds ``SKIP_RATIO`` times the
constraints'), nor where it could not change the answer: every estimated parameter
would move by at most ``MOVE_FRACTION`` of its std, and the std it would report is
never below the constraints'. Where tensors disagree (a near-planar scene) the
polish can change which triplets count, and always runs.

Its std is then the largest of the constraint solve's (which counts held and tied
values' uncertainty), its covariance's and its jackknife's. Otherwise everything is
returned unchanged.
Intrinsics in pixels; std relative to the focal length (θ units) unless named.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ...common.log import logger
from ...geometry.tensor_estimation import TripletTensor
from ..results import PARAMETER_NAMES
from ..solve.fallback import FallbackSolution
from ..solve.uncertainty import jackknife_covariance
from .bundle import PolishInput, TripletBundleResult, polish_intrinsics, predict_polish
from .camera_setup import pycolmap_camera_setup

#: Largest ratio of the polish's jackknife variance to the constraint solve's at
#: which the polish is kept when no more triplets agree with it than with the
#: constraints (with more: 1).
VARIANCE_RATIO = 0.5
#: Ratio of the predicted polish jackknife variance to the constraints' above which the
#: polish is not run: ``VARIANCE_RATIO`` with 10 % room for its further iterations
#: (where every tensor agrees the polish starts next to its optimum, and the first
#: step's prediction is within a few percent of the final ratio).
SKIP_RATIO = 1.1 * VARIANCE_RATIO
#: A polish predicted to move every estimated parameter by at most this fraction of
#: its std is not run: the estimate would stay well inside its uncertainty, and the
#: reported std would not narrow.
MOVE_FRACTION = 0.5


@dataclass
class Polished:
    """The estimate after the polish stage.

    Attributes:
        intrinsics: (fx, fy, cx, cy), pixels.
        relative_std: (4,) std relative to the focal length.
        agreeing: triplets that agree with ``intrinsics``.
        summary: the JSON ``triplet_bundle`` report, None when it did not run.
    """

    intrinsics: np.ndarray
    relative_std: np.ndarray
    agreeing: int
    summary: dict[str, Any] | None


def polish(given: PolishInput) -> Polished:
    """The polished estimate, or the constraint estimate with the reason it was kept."""
    tensors, tracks, start, estimate = given.tensors, given.tracks, given.start, given.estimate
    fallback, agreeing, camera_id, workers = (
        given.fallback,
        given.agreeing,
        given.camera_id,
        given.workers,
    )
    unchanged = Polished(estimate, fallback.relative_std, agreeing, None)
    free_parameters = fallback.free_parameters
    if pycolmap_camera_setup(free_parameters) is None:
        return unchanged
    focal_scale = np.array([start[0], start[1], start[0], start[1]])
    constraints = dict(zip(PARAMETER_NAMES, map(float, estimate), strict=True))
    skip = not_worth_it(tensors, tracks, start, estimate, fallback, focal_scale, workers)
    if skip:
        logger.info("camera %d: bundle adjustment of the triplets not run: %s", camera_id, skip)
        not_run = {"used": False, "agreeing": None, "constraints": constraints, "rejected": skip}
        return Polished(estimate, fallback.relative_std, agreeing, not_run)
    result = polish_intrinsics(given)
    summary: dict[str, object] = {
        "used": False,
        "agreeing": None if result is None else int(result.agreeing.sum()),
        "constraints": constraints,
    }
    why = rejected(result, focal_scale, fallback, agreeing)
    if why or result is None:
        logger.info("camera %d: bundle adjustment of the triplets not kept: %s", camera_id, why)
        summary["rejected"] = why
        return Polished(estimate, fallback.relative_std, agreeing, summary)
    summary["used"] = True
    relative_std = np.maximum(fallback.relative_std, result.std / focal_scale)
    logger.info(
        "camera %d: bundle adjustment of %d agreeing triplets: fx %.2f, fy %.2f, cx %.2f, "
        "cy %.2f px",
        camera_id,
        int(result.agreeing.sum()),
        *result.intrinsics,
    )
    return Polished(result.intrinsics, relative_std, int(result.agreeing.sum()), summary)


def not_worth_it(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    estimate: np.ndarray,
    fallback: FallbackSolution,
    focal_scale: np.ndarray,
    workers: int | None = None,
) -> str | None:
    """Why the polish cannot be kept, judged before it runs (see the module), or None."""
    if fallback.solution.jackknife is None or not np.all(fallback.solution.inlier_tensors):
        return None
    predicted = predict_polish(tensors, tracks, start, estimate, fallback.free_parameters, workers)
    if predicted is None:
        return None
    if predicted.jackknife_std is not None:
        polish_variance, constraint_variance = _variances(
            predicted.jackknife_std, focal_scale, fallback
        )
        if polish_variance > SKIP_RATIO * constraint_variance:
            return (
                f"its predicted jackknife spread ({np.sqrt(polish_variance):.2%}) exceeds "
                f"the constraints' ({np.sqrt(constraint_variance):.2%})"
            )
    estimated = _estimated(fallback)
    std = fallback.relative_std * focal_scale
    moves = np.abs(predicted.step[estimated]) / std[estimated]
    if moves.size and np.all(np.isfinite(moves)) and moves.max() <= MOVE_FRACTION:
        return f"its predicted move ({moves.max():.2f} std at most) cannot change the estimate"
    return None


def _estimated(fallback: FallbackSolution) -> np.ndarray:
    """(4,) bool: which of (fx, fy, cx, cy) the constraint solve estimated."""
    return np.asarray(
        fallback.free_parameters.parametrization(np.ones(4), np.ones(4)).matrix.any(axis=1)
    )


def _variances(
    polish_std: np.ndarray, focal_scale: np.ndarray, fallback: FallbackSolution
) -> tuple[float, float]:
    """Summed variances of the estimated parameters, relative to the focal length: the
    polish's (from its std in pixels) and the constraint solve's jackknife."""
    estimated = _estimated(fallback)
    assert fallback.solution.jackknife is not None
    constraint = np.diag(jackknife_covariance(fallback.solution.jackknife))
    return (
        float(np.sum((polish_std / focal_scale)[estimated] ** 2)),
        float(np.sum(constraint[estimated])),
    )


def rejected(
    result: TripletBundleResult | None,
    focal_scale: np.ndarray,
    fallback: FallbackSolution,
    agreeing: int,
) -> str | None:
    """Why the polish is not kept (see the module), or None."""
    if result is None:
        return "it failed"
    if int(result.agreeing.sum()) < agreeing:
        return (
            f"{int(result.agreeing.sum())} triplets agree with it, {agreeing} with the constraints"
        )
    if fallback.solution.jackknife is None or result.jackknife_std is None:
        return None
    polish_variance, constraint_variance = _variances(result.jackknife_std, focal_scale, fallback)
    limit = 1.0 if int(result.agreeing.sum()) > agreeing else VARIANCE_RATIO
    if polish_variance > limit * constraint_variance:
        return (
            f"its jackknife spread ({np.sqrt(polish_variance):.2%}) is not clearly below the "
            f"constraints' ({np.sqrt(constraint_variance):.2%})"
        )
    return None
