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

import numpy as np

from ..common.log import logger
from ..common.timing import StageClock
from ..database.cameras import CameraInfo
from ..database.snapshot import DatabaseContents
from .assessment import assess
from .camera_input import CameraInput, camera_input
from .focal_search import FocalSearchResult, search_focal
from .fundamental import calibrate_fundamental
from .lens_route import LensRoute, lens_search_applies, through_lens_search
from .method_run import MethodRun
from .options import CalibrationOptions
from .results import CameraCalibration
from .start_candidates import first_start
from .tensor_set import TensorEstimator
from .triplet_selection import CameraTracks, select_camera_triplets


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
    distortion, the lens search's warp (:mod:`.lens_route`) and everything again on
    the warped tracks first."""
    camera = data.camera
    run = MethodRun(data, tracks, estimator, method, options, clock)
    candidate = first_start(data.prior, search)
    route = LensRoute(None, 0, None)
    if lens_search_applies(run) and run.first_tensors_disagree(candidate, options.search_triplets):
        # Most of the first triplets disagree: the lens search, before the other tensors.
        route = through_lens_search(run)
    first = None
    if route.warped is None:
        # The restart waits for the lens search's verdict: on a lens it would refine
        # tensors the warp is about to replace.
        first = run.attempt(candidate, restart=False)
        if route.search is None and not first.majority_agrees and lens_search_applies(run):
            route = through_lens_search(run)
    # One budget for the camera's tensor work, the warped tracks' included.
    estimator.starts_used += route.spent
    if route.warped is not None:
        warped = route.warped
        data, tracks, search, finished = warped.data, warped.tracks, warped.search, warped.finished
    else:
        assert first is not None
        best = run.restarted(first)
        if not route.bent:
            best = run.best_attempt(best, search)
        # Else the raw tracks are bent and no warp made the tensors agree: other
        # focal lengths cannot either (the disagreement is the lens's, not the start's).
        finished = run.finish(best)
    best = finished.attempt
    # The lens is named as the cause only where the raw tracks' tensors disagreed too.
    finding = None if first is None or first.majority_agrees else route.finding()
    with clock("assessment"):
        result = assess(
            data,
            method,
            best.candidate,
            best.tensors.start,
            best.tensors.tensors,
            best.fallback,
            finished.polished,
            search,
            tracks.tracks,
            finished.lens,
            options.workers,
            finding,
        )
    result.seconds = clock.total
    result.stage_seconds = clock.as_dict()
    result.tensor_starts = estimator.starts_used
    logger.info("camera %d: %s", camera.camera_id, clock.summary())
    return result
