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

**A principal point the constraint solve held** (:func:`release_held`).
Each triplet's constraints say little about the principal point where its tracks
cover a small part of the image (an object capture, a ring around an object): the
solve holds it at the start. The agreeing triplets adjusted together with one
camera can still determine it, as a reconstruction of all the images would. The
polish is then first run with the principal point estimated as well, and kept
where at least as many triplets agree with it as with the constraints and its
curvature's std (``σ² (Σ H_t)⁻¹``) is within the solve's ``FALLBACK_FACTOR``
tolerances for every parameter it estimates; otherwise the polish runs as above.
The jackknife is not part of that test: where a few triplets carry most of what is
known about the principal point, leaving out a group of images moves it far, and
that spread is reported instead. The std of a parameter so estimated is the
polish's (the larger of its covariance's and its jackknife's), not the held value's
(docs/accuracy.md, seventeenth session).

**A focal length the constraint solve held** (the same :func:`release_held`). On a
sparse capture each triplet's constraints can know the focal length worse than the
fallback's standard, and the solve holds it at the start with everything else; the
triplets adjusted together with one camera can still determine it. The polish then
estimates one focal length and the principal point, under the same test, and where
at least ``MIN_FOCAL_TRIPLETS`` triplets and more than half of the tensors agree with
it (:func:`_too_few_for_a_focal_length`). On 30 of NeRF lego's renders from COLMAP's
guess (13.6 % off) the solve holds f with a std of 4 %; the adjustment of the 13
triplets gives it 1.5 % off with a std of 2.9 % (docs/accuracy.md, twenty-seventh
session).

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
from ..solve.observability import FALLBACK_FACTOR
from ..solve.parametrization import FreeParameters
from ..solve.theta import focal_scale
from ..solve.uncertainty import jackknife_covariance
from .bundle import (
    PolishInput,
    PredictedPolish,
    TripletBundleResult,
    polish_intrinsics,
    predict_polish,
)
from .calibrated_tracks import Observed, observed_tracks
from .camera_setup import camera_start, pycolmap_camera_setup
from .shared_camera import observed_at

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
#: A focal length the constraint solve held is estimated by the joint adjustment only
#: where at least this many triplets agree with it (:func:`_too_few_for_a_focal_length`).
MIN_FOCAL_TRIPLETS = 10


@dataclass
class Polished:
    """The estimate after the polish stage.

    Attributes:
        intrinsics: (fx, fy, cx, cy), pixels.
        relative_std: (4,) std relative to the focal length.
        agreeing: triplets that agree with ``intrinsics``.
        summary: the JSON ``triplet_bundle`` report, None when no adjustment ran.
        free_parameters: which of (fx, fy, cx, cy) ``intrinsics`` estimates: the
            constraint solve's, and the principal point and one focal length where the
            polish estimated what the solve held (:func:`release_held`).
    """

    intrinsics: np.ndarray
    relative_std: np.ndarray
    agreeing: int
    summary: dict[str, Any] | None
    free_parameters: FreeParameters


def polish(given: PolishInput) -> Polished:
    """The polished estimate, or the constraint estimate with the reason it was kept."""
    wider = released_parameters(given.fallback.free_parameters)
    if wider is None:
        return _polish_solved(given)
    # Both adjustments below start from the same tracks and projective costs.
    observed, cameras = _observed_for_release(given, wider)
    released, why_held = release_held(given, observed, wider, cameras)
    if released is not None:
        return released
    polished = _polish_solved(given, observed)
    if polished.summary is None:
        # Nothing else to adjust (the solve held every value): the release's is the report.
        polished.summary = {
            "used": False,
            "agreeing": None,
            "constraints": _by_name(given.estimate),
        }
    for name in _released_names(given.fallback.free_parameters):
        polished.summary[name] = f"held: {why_held}"
    return polished


def _observed_for_release(
    given: PolishInput, wider: FreeParameters
) -> tuple[list[Observed], dict[tuple[int, int, int], np.ndarray]]:
    """Each tensor's tracks and projective cost (:func:`.calibrated_tracks.observed_tracks`)
    and, by the tensor's images, its calibrated cameras at the start of the adjustment of
    ``wider`` where they could be formed, computed together (one call to the workers:
    :func:`.shared_camera.observed_at`); no cameras where pycolmap cannot express
    ``wider``."""
    start_values = camera_start(wider, given.estimate)
    if start_values is None:
        observed = observed_tracks(given.tensors, given.tracks, given.start, workers=given.workers)
        return observed, {}
    observed, formed = observed_at(
        given.tensors, given.tracks, given.start, start_values[1], workers=given.workers
    )
    cameras = {
        triplet.tensor.image_ids: camera
        for triplet, camera in zip(observed, formed, strict=True)
        if camera is not None
    }
    return observed, cameras


def released_parameters(solved: FreeParameters) -> FreeParameters | None:
    """What :func:`release_held` may estimate where the constraint solve held values: the
    principal point, and one focal length where the solve held it; None where the solve
    held nothing of that."""
    wider = FreeParameters("tied" if solved.focal == "held" else solved.focal, cx=True, cy=True)
    return None if wider == solved else wider


def _released_names(solved: FreeParameters) -> list[str]:
    """The summary keys of what :func:`released_parameters` releases of ``solved``."""
    names = ["focal_length"] if solved.focal == "held" else []
    if not (solved.cx and solved.cy):
        names.append("principal_point")
    return names


def _by_name(intrinsics: np.ndarray) -> dict[str, float]:
    """(fx, fy, cx, cy), pixels, as the JSON report's ``{"fx": ..., ...}``."""
    return dict(zip(PARAMETER_NAMES, map(float, intrinsics), strict=True))


def _polish_solved(given: PolishInput, observed: list[Observed] | None = None) -> Polished:
    """The polish of the parameters the constraint solve estimated (see the module);
    ``observed``: the tensors' tracks and projective costs where already computed."""
    tensors, tracks, start, estimate = given.tensors, given.tracks, given.start, given.estimate
    fallback, agreeing, camera_id, workers = (
        given.fallback,
        given.agreeing,
        given.camera_id,
        given.workers,
    )
    free_parameters = fallback.free_parameters
    unchanged = Polished(estimate, fallback.relative_std, agreeing, None, free_parameters)
    if pycolmap_camera_setup(free_parameters) is None:
        return unchanged
    scale = focal_scale(start)
    constraints = _by_name(estimate)
    skip, predicted = not_worth_it(tensors, tracks, start, estimate, fallback, scale, workers)
    if skip:
        logger.info("camera %d: bundle adjustment of the triplets not run: %s", camera_id, skip)
        not_run = {"used": False, "agreeing": None, "constraints": constraints, "rejected": skip}
        return Polished(estimate, fallback.relative_std, agreeing, not_run, free_parameters)
    result = polish_intrinsics(
        given, observed=observed, cameras=None if predicted is None else predicted.cameras
    )
    summary: dict[str, object] = {
        "used": False,
        "agreeing": None if result is None else int(result.agreeing.sum()),
        "constraints": constraints,
    }
    why = rejected(result, scale, fallback, agreeing)
    if why or result is None:
        logger.info("camera %d: bundle adjustment of the triplets not kept: %s", camera_id, why)
        summary["rejected"] = why
        return Polished(estimate, fallback.relative_std, agreeing, summary, free_parameters)
    summary["used"] = True
    relative_std = np.maximum(fallback.relative_std, result.std / scale)
    _log_kept(camera_id, result)
    return Polished(
        result.intrinsics, relative_std, int(result.agreeing.sum()), summary, free_parameters
    )


def release_held(
    given: PolishInput,
    observed: list[Observed],
    wider: FreeParameters,
    cameras: dict[tuple[int, int, int], np.ndarray] | None = None,
) -> tuple[Polished | None, str | None]:
    """The polish with ``wider`` estimated (:func:`released_parameters`: what the
    constraint solve held; see the module) and None, or None and why those values stay
    held. ``observed``: the tensors' tracks and projective costs; ``cameras``: their
    calibrated cameras at the adjustment's start where already formed (by the tensor's
    images)."""
    fallback, start = given.fallback, given.start
    result = polish_intrinsics(given, wider, observed=observed, cameras=cameras)
    scale = focal_scale(start)
    why = _not_determined(result, wider, scale, fallback.tolerances, given.agreeing)
    names = _released_names(fallback.free_parameters)
    if why is None and result is not None and "focal_length" in names:
        why = _too_few_for_a_focal_length(result, len(given.tensors))
    if why or result is None:
        logger.info(
            "camera %d: the %s held: %s",
            given.camera_id,
            " and the ".join(name.replace("_", " ") for name in names)
            + (" stay" if len(names) > 1 else " stays"),
            why,
        )
        return None, why
    # The solve's estimated parameters keep at least its std (as in the polish);
    # what it held has the polish's own, not the held value's.
    relative_std = result.std / scale
    relative_std = np.where(
        _estimated(fallback), np.maximum(fallback.relative_std, relative_std), relative_std
    )
    summary: dict[str, object] = {
        "used": True,
        "agreeing": int(result.agreeing.sum()),
        "constraints": _by_name(given.estimate),
    }
    for name in names:
        summary[name] = "estimated by the adjustment (the constraint solve held it)"
    _log_kept(given.camera_id, result)
    kept = Polished(result.intrinsics, relative_std, int(result.agreeing.sum()), summary, wider)
    return kept, None


def _not_determined(
    result: TripletBundleResult | None,
    free_parameters: FreeParameters,
    scale: np.ndarray,
    tolerances: np.ndarray,
    agreeing: int,
) -> str | None:
    """Why an adjustment of ``free_parameters`` does not determine them: it is not
    supported (:func:`_unsupported`), or the std of its curvature exceeds
    ``FALLBACK_FACTOR`` tolerances for one of them; None when it determines them.
    ``scale``: :func:`focal_scale` of the start."""
    why = _unsupported(result, agreeing)
    if why or result is None:
        return why
    estimated = _estimated_by(free_parameters)
    ratios = (result.covariance_std / scale / tolerances)[estimated]
    if not np.all(np.isfinite(ratios)) or ratios.max() >= FALLBACK_FACTOR:
        ranked = np.where(np.isfinite(ratios), ratios, np.inf)
        worst = PARAMETER_NAMES[int(np.flatnonzero(estimated)[np.argmax(ranked)])]
        return f"it leaves {worst} beyond {FALLBACK_FACTOR:g} tolerances"
    return None


def _too_few_for_a_focal_length(result: TripletBundleResult, tensors: int) -> str | None:
    """Why a focal length the constraint solve held stays held although the adjustment
    determines it (None where it does not): fewer than ``MIN_FOCAL_TRIPLETS`` triplets
    agree with the adjustment, or at most half the tensors.

    A few triplets' adjustment knows less than its std says: on the first 20 of NeRF
    lego's renders, 8 agreeing triplets over 12 images put cx 18.6 px off with a std of
    5.9 px on every start, and from a ±5 % prior the result ended 0.19 % further from the
    truth than the prior (pycolmap's mapping of those images has cx 20 px off too). Where
    the adjustment determined f on the real subsets, 13–16 triplets agreed with it
    (lego's 30 renders) and 14 (KITTI's last 11 frames), every error within 1.3 std. And a
    focal length is what the tensors' consensus decides, as where the focal search's
    value is held (:func:`..tensors.attempts.held_where_nothing_agrees`): a minority's
    adjustment would stand for all of them.
    """
    kept = int(result.agreeing.sum())
    if kept < MIN_FOCAL_TRIPLETS:
        return f"{kept} triplets agree with it, fewer than {MIN_FOCAL_TRIPLETS}"
    if 2 * kept <= tensors:
        return f"{kept} of {tensors} triplets agree with it, not a majority"
    return None


def _unsupported(result: TripletBundleResult | None, agreeing: int) -> str | None:
    """Why an adjustment cannot replace the constraint estimate whatever its spread: it
    failed, or fewer triplets agree with it than with the constraints (``agreeing``);
    None otherwise."""
    if result is None:
        return "it failed"
    kept = int(result.agreeing.sum())
    if kept < agreeing:
        return f"{kept} triplets agree with it, {agreeing} with the constraints"
    return None


def _log_kept(camera_id: int, result: TripletBundleResult) -> None:
    logger.info(
        "camera %d: bundle adjustment of %d agreeing triplets: fx %.2f, fy %.2f, cx %.2f, "
        "cy %.2f px",
        camera_id,
        int(result.agreeing.sum()),
        *result.intrinsics,
    )


def not_worth_it(
    tensors: list[TripletTensor],
    tracks: dict[tuple[int, int, int], np.ndarray],
    start: np.ndarray,
    estimate: np.ndarray,
    fallback: FallbackSolution,
    scale: np.ndarray,
    workers: int | None = None,
) -> tuple[str | None, PredictedPolish | None]:
    """Why the polish cannot be kept, judged before it runs (see the module), or None;
    and the prediction it was judged by (None where it was not made)."""
    if fallback.solution.jackknife is None or not np.all(fallback.solution.inlier_tensors):
        return None, None
    predicted = predict_polish(tensors, tracks, start, estimate, fallback.free_parameters, workers)
    if predicted is None:
        return None, None
    if predicted.jackknife_std is not None:
        polish_variance, constraint_variance = _variances(predicted.jackknife_std, scale, fallback)
        if polish_variance > SKIP_RATIO * constraint_variance:
            return (
                f"its predicted jackknife spread ({np.sqrt(polish_variance):.2%}) exceeds "
                f"the constraints' ({np.sqrt(constraint_variance):.2%})"
            ), predicted
    estimated = _estimated(fallback)
    std = fallback.relative_std * scale
    moves = np.abs(predicted.step[estimated]) / std[estimated]
    if moves.size and np.all(np.isfinite(moves)) and moves.max() <= MOVE_FRACTION:
        why = f"its predicted move ({moves.max():.2f} std at most) cannot change the estimate"
        return why, predicted
    return None, predicted


def _estimated(fallback: FallbackSolution) -> np.ndarray:
    """(4,) bool: which of (fx, fy, cx, cy) the constraint solve estimated."""
    return _estimated_by(fallback.free_parameters)


def _estimated_by(free_parameters: FreeParameters) -> np.ndarray:
    """(4,) bool: which of (fx, fy, cx, cy) ``free_parameters`` estimate (a tied fy counts)."""
    return np.asarray(free_parameters.parametrization(np.ones(4), np.ones(4)).matrix.any(axis=1))


def _variances(
    polish_std: np.ndarray, scale: np.ndarray, fallback: FallbackSolution
) -> tuple[float, float]:
    """Summed variances of the estimated parameters, relative to the focal length: the
    polish's (from its std in pixels) and the constraint solve's jackknife."""
    estimated = _estimated(fallback)
    assert fallback.solution.jackknife is not None
    constraint = np.diag(jackknife_covariance(fallback.solution.jackknife))
    return (
        float(np.sum((polish_std / scale)[estimated] ** 2)),
        float(np.sum(constraint[estimated])),
    )


def rejected(
    result: TripletBundleResult | None,
    scale: np.ndarray,
    fallback: FallbackSolution,
    agreeing: int,
) -> str | None:
    """Why the polish is not kept (see the module), or None."""
    why = _unsupported(result, agreeing)
    if why or result is None:
        return why
    if fallback.solution.jackknife is None or result.jackknife_std is None:
        return None
    polish_variance, constraint_variance = _variances(result.jackknife_std, scale, fallback)
    limit = 1.0 if int(result.agreeing.sum()) > agreeing else VARIANCE_RATIO
    if polish_variance > limit * constraint_variance:
        return (
            f"its jackknife spread ({np.sqrt(polish_variance):.2%}) is not clearly below the "
            f"constraints' ({np.sqrt(constraint_variance):.2%})"
        )
    return None
