"""One physical camera, stage by stage.

    data     = camera_input(contents, camera, images)            # read: prior, keypoints
    tracks   = select_camera_triplets(data, images)               # tracks
    search   = search_focal(tracks, prior)                        # focal_search
    for each start candidate (the first; other starts while most tensors disagree):
        tensors  = estimator.at(start, previous)                  # tensors (reused)
        solution = solve_with_fallback(tensors, start)            # solve (and a restart)
        (most disagree at the first start, a radial model with no distortion stored:
         warp = search_lens(tracks)                                # lens_search
         the same on the warped tracks, from the warp's focal length)
    polished = polish(solution, tracks)                            # polish (msac-opt)
    lens     = estimate_distortion(polished, raw tracks)           # polish (msac-opt)
    result   = assess(polished, lens, solution)                    # assessment

Each line is one stage with a typed input and output; the seconds of each go into the
result (:class:`..common.timing.StageClock`). Intrinsics in pixels, COLMAP's pixel
convention (the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace

import numpy as np

from ..common.errors import CalibrationError
from ..common.log import logger
from ..common.timing import StageClock
from ..database.cameras import CameraInfo
from ..database.snapshot import DatabaseContents
from .assessment import assess
from .camera_input import CameraInput, camera_input
from .focal_search import FocalSearchResult, search_focal
from .fundamental import calibrate_fundamental
from .lens_distortion import LensDistortion, LensStart, distortion_model, estimate_distortion
from .lens_search import LensSearchResult, polynomial_start, search_lens
from .observability import tolerance
from .options import CalibrationOptions
from .parametrization import FULL, HELD, SINGLE_FOCAL, FreeParameters
from .polish import Polished, polish
from .results import CameraCalibration
from .selfcalibration import (
    FallbackProblem,
    FallbackSolution,
    fold_focal_sign,
    solve_with_fallback,
    theta_to_intrinsics,
)
from .start_candidates import StartCandidate, first_start, moved_far, other_starts, restart_point
from .tensor_set import TensorEstimator, TensorSet
from .triplet_selection import CameraTracks, select_camera_triplets

#: Radial terms (k1[, k2]) of the stored models the lens search can start, COLMAP's
#: order (they come first among the model's distortion parameters).
RADIAL_PARAMETERS = {"SIMPLE_RADIAL": 1, "RADIAL": 2, "OPENCV": 2}
#: Tensors that must agree with an estimate for it to stand (fewer when the camera
#: has fewer triplets): below, every value is held at the start.
MIN_AGREEING = 3


@dataclass
class Attempt:
    """The solve from one start candidate: its tensors, where they ended normalised, the solve."""

    candidate: StartCandidate
    tensors: TensorSet
    fallback: FallbackSolution

    @property
    def agreeing(self) -> int:
        """Tensors that agree with (are MSAC inliers at) the estimate."""
        return int(self.fallback.solution.inlier_tensors.sum())

    @property
    def majority_agrees(self) -> bool:
        """At least half the tensors agree: no other start is tried."""
        return 2 * self.agreeing >= len(self.fallback.solution.inlier_tensors)


@dataclass
class _Warped:
    """A run on the lens search's warped tracks (:func:`_through_lens_search`): its
    input and tracks (warped), the warp's focal search, the attempt, its polish and the
    lens stage that adjusted the stored model's distortion from the raw tracks."""

    data: CameraInput
    tracks: CameraTracks
    search: FocalSearchResult
    attempt: Attempt
    polished: Polished
    lens: LensDistortion


def calibrate_camera(
    contents: DatabaseContents,
    camera: CameraInfo,
    image_ids: list[int],
    options: CalibrationOptions,
    methods: tuple[str, ...],
) -> dict[str, CameraCalibration]:
    """Estimate one camera from the triplets of ``image_ids``, with each of ``methods``.

    ``camera`` gives the model, size and prior; the images may belong to several camera
    ids of one group, and each image's keypoints are undistorted with its own camera.
    The trifocal methods share the tracks, the focal search and the tensors; each
    result's ``stage_seconds`` holds the shared stages and its own.
    """
    clock = StageClock()
    with clock("read"):
        data = camera_input(contents, camera, image_ids, options)
    read_clock = copy.deepcopy(clock)
    results: dict[str, CameraCalibration] = {}
    trifocal = [m for m in methods if m != "fundamental"]
    if trifocal:
        with clock("tracks"):
            tracks = select_camera_triplets(data, image_ids, options)
        seeds = np.random.SeedSequence(options.seed).spawn(len(tracks.triplets) + 1)
        with clock("focal_search"):
            search = _search_focal(data, tracks, seeds[-1], options)
        estimator = TensorEstimator(tracks, camera.camera_id, options, seeds[:-1])
        for method in trifocal:
            method_clock = copy.deepcopy(clock)
            results[method] = _calibrate_method(
                data, tracks, search, estimator, method, options, method_clock
            )
    if "fundamental" in methods:
        with read_clock("solve"):
            results["fundamental"] = calibrate_fundamental(data)
        results["fundamental"].seconds = read_clock.total
        results["fundamental"].stage_seconds = read_clock.as_dict()
    return {method: results[method] for method in methods}


def _search_focal(
    data: CameraInput,
    tracks: CameraTracks,
    seed: np.random.SeedSequence,
    options: CalibrationOptions,
) -> FocalSearchResult | None:
    """The focal search over the first ``options.search_triplets`` triplets (None: off)."""
    if not options.focal_search:
        return None
    camera = data.camera
    found = search_focal(
        tracks.tracks[: options.search_triplets],
        data.prior,
        np.random.default_rng(seed),
        options.tensor.inlier_threshold_px,
        workers=options.workers,
        progress=options.progress,
        image_size=(camera.width, camera.height),
    )
    logger.info(
        "camera %d: focal search: %.1f px (std %.1f %%, %s, %s)",
        camera.camera_id,
        found.focal,
        100 * found.relative_std,
        "decisive" if found.decisive else "not decisive",
        "used" if found.improves_on_start else "the start explains the tracks as well: kept",
    )
    return found


def _calibrate_method(
    data: CameraInput,
    tracks: CameraTracks,
    search: FocalSearchResult | None,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
) -> CameraCalibration:
    """One trifocal variant: the start candidates, the polish and the assessment; where
    most tensors disagree at the first start on a camera that may hold radial
    distortion, the lens search's warp (:mod:`.lens_search`) and everything again on
    the warped tracks first."""
    camera = data.camera
    # The restart waits for the lens search's verdict: on a lens it would refine tensors
    # the warp is about to replace.
    candidate = first_start(data.prior, search)
    first = _attempt(candidate, None, data, estimator, method, options, clock, restart=False)
    warped: _Warped | None = None
    lens: LensDistortion | None = None
    spent = 0
    if not first.majority_agrees and _lens_search_applies(camera, method, options):
        warped, spent = _through_lens_search(data, tracks, estimator, method, options, clock)
    if warped is not None:
        data, tracks, search = warped.data, warped.tracks, warped.search
        best, polished, lens = warped.attempt, warped.polished, warped.lens
    else:
        first = _restarted(first, data, estimator, method, options, clock)
        best = _best_attempt(first, data, tracks, search, estimator, method, options, clock)
        best, polished, lens = _finish(data, tracks, best, method, options, clock)
    with clock("assessment"):
        result = assess(
            data,
            method,
            best.candidate,
            best.tensors.start,
            best.tensors.tensors,
            best.fallback,
            polished,
            search,
            tracks.tracks,
            lens,
            options.workers,
        )
    result.seconds = clock.total
    result.stage_seconds = clock.as_dict()
    result.tensor_starts = estimator.starts_used + spent
    logger.info("camera %d: %s", camera.camera_id, clock.summary())
    return result


def _best_attempt(
    first: Attempt,
    data: CameraInput,
    tracks: CameraTracks,
    search: FocalSearchResult | None,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
) -> Attempt:
    """The first start's attempt, or the other starts' best while most tensors disagree."""
    best = first
    for candidate in other_starts(search, first.candidate, best.tensors.start, method, options):
        if best.majority_agrees or not estimator.can_afford(len(tracks.triplets)):
            break
        logger.info(
            "camera %d: %d of %d tensors agree; estimating them again from f = %.1f px "
            "(focal search)",
            data.camera.camera_id,
            best.agreeing,
            len(best.fallback.solution.inlier_tensors),
            candidate.start[0],
        )
        other = _attempt(candidate, best.tensors, data, estimator, method, options, clock)
        if other.agreeing > best.agreeing:
            best = other
    return best


def _finish(
    data: CameraInput,
    tracks: CameraTracks,
    best: Attempt,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
    warp: LensSearchResult | None = None,
    raw: dict[tuple[int, int, int], np.ndarray] | None = None,
) -> tuple[Attempt, Polished, LensDistortion | None]:
    """The estimate (every value held where nothing agrees), its polish and the lens
    stage; ``tracks`` warped by ``warp`` from the ``raw`` ones (per triplet, pixels) have
    the distortion adjusted from the raw tracks, started from the warp's polynomial."""
    camera = data.camera
    with clock("solve"):
        if _nothing_agrees(best, method):
            logger.info(
                "camera %d: %d of %d tensors agree with the estimate: every value held",
                camera.camera_id,
                best.agreeing,
                len(best.tensors.tensors),
            )
            best = Attempt(
                best.candidate,
                best.tensors,
                _solve(best.candidate, best.tensors, data, method, options, HELD),
            )
        start, fallback = best.tensors.start, best.fallback
        estimate = _checked_estimate(best, camera.camera_id, method)
    with clock("polish"):
        polished = Polished(estimate, fallback.relative_std, best.agreeing, None)
        if method == "msac-opt" and options.triplet_bundle:
            polished = polish(
                best.tensors.tensors,
                tracks.by_images(),
                start,
                estimate,
                fallback,
                best.agreeing,
                (camera.width, camera.height),
                options.tau,
                camera.camera_id,
                options.workers,
            )
        lens = None
        if method == "msac-opt" and options.triplet_bundle:
            observed = None
            if warp is not None and raw is not None:
                observed = LensStart(raw, _distortion_start(camera, warp, raw, polished.intrinsics))
            lens = estimate_distortion(
                best.tensors.tensors,
                tracks.by_images(),
                start,
                polished.intrinsics,
                fallback.free_parameters,
                camera,
                options.tau,
                fallback.solution.inlier_tensors,
                options.workers,
                observed,
            )
    return best, polished, lens


def _lens_search_applies(camera: CameraInfo, method: str, options: CalibrationOptions) -> bool:
    """Whether the lens search may run: the polished variant, a focal search, and a
    stored model with radial distortion that holds none yet (a pinhole stays pinhole)."""
    return (
        method == "msac-opt"
        and options.triplet_bundle
        and options.focal_search
        and distortion_model(camera) == camera.model
        and camera.model in RADIAL_PARAMETERS
    )


def _through_lens_search(
    data: CameraInput,
    tracks: CameraTracks,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
) -> tuple[_Warped | None, int]:
    """The run on the lens search's warped tracks, and the refinement starts it spent;
    None where the search finds no clear warp, the tensors agree on none of its warps
    (:meth:`.LensSearchResult.candidates`), or the lens stage does not confirm the
    distortion (the unwarped run then goes on as it would have)."""
    camera = data.camera
    size = (camera.width, camera.height)
    rng = np.random.default_rng(
        np.random.SeedSequence(options.seed, spawn_key=(len(tracks.triplets) + 1,))
    )
    with clock("lens_search"):
        found = search_lens(
            tracks.tracks[: options.search_triplets],
            data.prior,
            rng,
            options.tensor.inlier_threshold_px,
            size,
            options.workers,
        )
    logger.info(
        "camera %d: lens search: division %.2f, %.1f px (the unwarped tracks cost %.1fx; %s)",
        camera.camera_id,
        found.division,
        found.focal.focal,
        found.ratio,
        "used" if found.clear else "not clear: not used",
    )
    if not found.clear:
        return None, 0
    spent = 0
    for division in found.candidates():
        warp = replace(found, division=division)
        keypoints = {image: warp.undistort(k) for image, k in data.keypoints.items()}
        warped_data = CameraInput(camera, data.prior, keypoints, data.matches)
        warped = CameraTracks(
            tracks.triplets, [warp.undistort(x) for x in tracks.tracks], tracks.sequence
        )
        warped_estimator = TensorEstimator(warped, camera.camera_id, options, estimator.seeds)
        # One start per warp: where its tensors do not agree, the next warp, then the
        # unwarped run as it would have gone on.
        start = first_start(data.prior, warp.focal)
        best = _attempt(start, None, warped_data, warped_estimator, method, options, clock)
        spent += warped_estimator.starts_used
        if not _nothing_agrees(best, method):
            break
        logger.info(
            "camera %d: %d of %d tensors agree on the tracks warped with division %.2f",
            camera.camera_id,
            best.agreeing,
            len(best.tensors.tensors),
            division,
        )
    else:
        return None, spent
    best, polished, lens = _finish(
        warped_data, warped, best, method, options, clock, warp, tracks.by_images()
    )
    if lens is None or not lens.present:
        logger.info(
            "camera %d: the lens adjustment did not confirm the warp: not used", camera.camera_id
        )
        return None, spent
    return _Warped(warped_data, warped, warp.focal, best, polished, lens), spent


def _distortion_start(
    camera: CameraInfo,
    warp: LensSearchResult,
    raw: dict[tuple[int, int, int], np.ndarray],
    intrinsics: np.ndarray,
) -> np.ndarray:
    """The stored model's distortion (COLMAP's order) nearest the warp at ``intrinsics``:
    its radial terms fitted out to the farthest raw track, the rest 0."""
    farthest = max(float(np.max(np.linalg.norm(x - warp.centre, axis=-1))) for x in raw.values())
    radial = polynomial_start(warp, intrinsics, RADIAL_PARAMETERS[camera.model], farthest)
    start = np.zeros(len(camera.distortion))
    start[: len(radial)] = radial
    return start


def _attempt(
    candidate: StartCandidate,
    previous: TensorSet | None,
    data: CameraInput,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
    restart: bool = True,
) -> Attempt:
    """The tensors at a start, their solve, and (``restart``) the restart when the
    estimate lands far (:func:`_restarted`)."""
    with clock("tensors"):
        tensors = estimator.at(candidate.start, previous)
    attempt = _solved(candidate, tensors, data, estimator, method, options, clock)
    return _restarted(attempt, data, estimator, method, options, clock) if restart else attempt


def _restarted(
    attempt: Attempt,
    data: CameraInput,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
) -> Attempt:
    """The attempt with its disagreeing tensors estimated again from its estimate and
    solved again, where the estimate landed far from the start (else as it is)."""
    tensors = attempt.tensors
    point = restart_point(attempt.fallback, tensors.start)
    if (
        options.restart
        and method != "direct"
        and moved_far(point, tensors.start)
        and estimator.can_afford(len(tensors.by_triplet))
    ):
        logger.info(
            "camera %d: estimate far from the start; estimating the disagreeing tensors again",
            data.camera.camera_id,
        )
        with clock("tensors"):
            tensors = estimator.at(point, attempt.tensors)
        attempt = _solved(attempt.candidate, tensors, data, estimator, method, options, clock)
    return attempt


def _solved(
    candidate: StartCandidate,
    tensors: TensorSet,
    data: CameraInput,
    estimator: TensorEstimator,
    method: str,
    options: CalibrationOptions,
    clock: StageClock,
) -> Attempt:
    """The solve of ``tensors``; the disagreeing ones refined from both starts and solved
    again, where enough tensors agree to say which K the second start is from (with fewer
    than ``MIN_AGREEING`` the start is as doubtful as the tensors: other starts follow)."""
    with clock("solve"):
        fallback = _solve(candidate, tensors, data, method, options)
    if not _consensus(fallback):
        return Attempt(candidate, tensors, fallback)
    with clock("tensors"):
        second = estimator.with_second_starts(tensors, ~fallback.solution.inlier_tensors)
    if second is not None:
        tensors = second
        with clock("solve"):
            fallback = _solve(candidate, tensors, data, method, options)
    return Attempt(candidate, tensors, fallback)


def _solve(
    candidate: StartCandidate,
    tensors: TensorSet,
    data: CameraInput,
    method: str,
    options: CalibrationOptions,
    base: FreeParameters | None = None,
) -> FallbackSolution:
    """The 15 constraints of ``tensors`` solved with ``method`` for the parameters of
    ``base`` (default: the camera model's); undetermined parameters tied (fy = fx) or
    held at the candidate's values (:func:`.solve_with_fallback`)."""
    camera = data.camera
    problem = FallbackProblem(
        tensors.tensors,
        method,
        tensors.start,
        candidate.held,
        tolerance(tensors.start, camera.width, camera.height),
        options.tau,
        candidate.held_std,
    )
    if base is None:
        base = SINGLE_FOCAL if camera.single_focal else FULL
    return solve_with_fallback(problem, base)


def _nothing_agrees(attempt: Attempt, method: str) -> bool:
    """Whether fewer than ``MIN_AGREEING`` tensors agree with the estimate of a robust
    method that estimated something: the tracks single out no K (strong unmodelled
    lens distortion, wrong matches, no parallax), and the start is the best evidence
    the run has."""
    return (
        method != "direct"
        and attempt.fallback.free_parameters.dimension > 0
        and not _consensus(attempt.fallback)
    )


def _consensus(fallback: FallbackSolution) -> bool:
    """Whether at least ``MIN_AGREEING`` tensors (all, when there are fewer) agree with
    the estimate: one or two tensors among many that agree with a K are as likely to
    agree by chance as because it is the camera's."""
    inliers = fallback.solution.inlier_tensors
    return int(inliers.sum()) >= min(MIN_AGREEING, len(inliers))


def _checked_estimate(best: Attempt, camera_id: int, method: str) -> np.ndarray:
    """The estimate (fx, fy, cx, cy) in pixels, or CalibrationError when it is garbage
    (not finite, a focal length ≤ 0 that tensors agree with)."""
    fallback = best.fallback
    estimate = fold_focal_sign(theta_to_intrinsics(fallback.solution.theta, best.tensors.start))
    checked = method != "direct" and fallback.free_parameters.dimension > 0
    if not (
        np.all(np.isfinite(estimate)) and min(estimate[:2]) > 0 and (best.agreeing or not checked)
    ):
        raise CalibrationError(
            f"camera {camera_id}: no valid estimate (fx {estimate[0]:.4g}, fy "
            f"{estimate[1]:.4g}; {best.agreeing} of {len(best.tensors.tensors)} tensors agree): "
            "too little parallax or wrong matches"
        )
    if fallback.free_parameters.assumptions():
        logger.info(
            "camera %d: assumed %s", camera_id, "; ".join(fallback.free_parameters.assumptions())
        )
    return estimate
