"""The polish stage: msac-opt's estimate replaced by the triplets' shared-camera bundle
adjustment (:mod:`.triplet_bundle`) where that is at least as well supported.

The bundle adjustment replaces the constraint estimate when

* at least as many triplets agree with it (λ < τ²) as tensors did (‖r‖ < τ), and
* its image jackknife variance is at most ``VARIANCE_RATIO`` times the constraint
  solve's: the sum of the estimated parameters' jackknife variances relative to the
  focal length, over the same image groups (the polish's replicates are one
  Gauss–Newton step each on the triplets' Schur complements,
  :mod:`.bundle_information`). Two such variances from ten image groups differ by
  a factor of two by chance in about one case in five: the polish replaces the
  constraint estimate only on clear evidence that it is the tighter one, as on
  near-planar scenes, where the first-order whitening of the constraints fails.

Its std is then the largest of the constraint solve's (which counts held and tied
values' uncertainty), its covariance's and its jackknife's. Otherwise everything is
returned unchanged.
Intrinsics in pixels; std relative to the focal length (θ units) unless named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..common.log import logger
from ..geometry.tensor_estimation import TripletTensor
from .results import PARAMETER_NAMES
from .selfcalibration import FallbackSolution
from .triplet_bundle import TripletBundleResult, polish_intrinsics, pycolmap_camera_setup
from .uncertainty import jackknife_covariance

#: Largest ratio of the polish's jackknife variance to the constraint solve's at
#: which the polish is kept.
VARIANCE_RATIO = 0.5


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
    summary: dict | None


def polish(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    estimate: np.ndarray,
    fallback: FallbackSolution,
    agreeing: int,
    size: tuple[int, int],
    tau: float,
    camera_id: int,
) -> Polished:
    """The polished estimate, or the constraint estimate with the reason it was kept.

    Args:
        tensors: the solve's tensors, normalised by ``start`` (pixels).
        tracks: per triplet (image ids), its tracks (3, n, 2), pixels.
        estimate: the constraint estimate (fx, fy, cx, cy), pixels.
        fallback: the constraint solve (model, std, jackknife).
        agreeing: tensors that agree with ``estimate``.
        size: (width, height) of the images, pixels.
        tau: the MSAC threshold.
    """
    unchanged = Polished(estimate, fallback.relative_std, agreeing, None)
    model = fallback.model
    if pycolmap_camera_setup(model) is None:
        return unchanged
    result = polish_intrinsics(tensors, tracks, start, estimate, model, size, tau)
    summary = {
        "used": False,
        "agreeing": None if result is None else int(result.agreeing.sum()),
        "constraints": dict(zip(PARAMETER_NAMES, map(float, estimate), strict=True)),
    }
    focal_scale = np.array([start[0], start[1], start[0], start[1]])
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
    replicates = fallback.solution.jackknife
    if replicates is None or result.jackknife_std is None:
        return None
    estimated = fallback.model.parametrization(np.ones(4), np.ones(4)).matrix.any(axis=1)
    polish_variance = float(np.sum((result.jackknife_std / focal_scale)[estimated] ** 2))
    constraint_variance = float(np.sum(np.diag(jackknife_covariance(replicates))[estimated]))
    if polish_variance > VARIANCE_RATIO * constraint_variance:
        return (
            f"its jackknife spread ({np.sqrt(polish_variance):.2%}) is not clearly below the "
            f"constraints' ({np.sqrt(constraint_variance):.2%})"
        )
    return None
