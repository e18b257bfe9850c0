"""One physical camera, stage by stage: the stage list.

    data     = camera_input(contents, camera, images)        # inputs: prior, keypoints
    tracks   = select_camera_triplets(data, images)           # inputs: triplets, tracks
    search   = search_focal(tracks, prior)                    # start: the focal search
    start    = first_start(prior, search)                     # start
    per method (msac-opt, msac, direct):
      [lens]   where the first tensors disagree on a radial camera that stores no
               distortion: find_warp, and attempts on the warped tracks per warp
      first    = attempt(start)                               # tensors + solve
      [lens]   where most tensors still disagree: the same
      best     = restarted(first); best_attempt(best)         # restart, other starts
      best     = held_where_nothing_agrees(best)              # hold
      polished = polish(best, tracks)                         # polish (msac-opt)
      lens     = estimate_distortion(polished, raw tracks)    # distortion (msac-opt)
      result   = assess(polished, lens, best)                 # assessment

Each stage is a function of its own module with a typed input and output, called
from here only; the seconds of each go into the result
(:class:`..common.timing.StageClock`; the distortion stage counts as ``polish``).
Intrinsics in pixels, COLMAP's pixel convention (the centre of the top-left pixel at
(0.5, 0.5)).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..common.log import logger
from ..common.timing import StageClock
from ..database.cameras import CameraInfo
from ..database.snapshot import DatabaseContents
from .assess.assessment import AssessInput, assess
from .baselines.fundamental import calibrate_fundamental
from .inputs.camera_input import CameraInput, camera_input
from .inputs.prior import default_guess
from .inputs.triplet_selection import CameraTracks, select_camera_triplets
from .lens.distortion import DistortionInput, LensDistortion, LensStart, estimate_distortion
from .lens.search import LensSearchResult
from .lens.warp import (
    bent_tracks_finding,
    find_warp,
    lens_search_applies,
    warped_input,
)
from .options import CalibrationOptions
from .polish.bundle import PolishInput
from .polish.stage import Polished, polish
from .results import CameraCalibration, Timing
from .start.candidates import StartCandidate, first_start
from .start.focal_search import FocalSearchResult, search_focal
from .tensors.attempts import (
    Attempt,
    AttemptInputs,
    attempt,
    best_attempt,
    checked_estimate,
    consensus,
    first_tensors_disagree,
    focal_held_against_most,
    held_where_nothing_agrees,
    majority_of,
    restarted,
)
from .tensors.estimator import TensorEstimator


@dataclass
class Finished:
    """The chosen attempt (its values held where nothing agrees), its polish and the
    lens stage (None where it does not apply)."""

    attempt: Attempt
    polished: Polished
    lens: LensDistortion | None


@dataclass
class Warped:
    """A run on the lens search's warped tracks: its inputs (warped), the warp's focal
    search (a clear warp's: never None), and what it finished with (the lens stage
    having adjusted the stored model's distortion from the raw tracks)."""

    inputs: AttemptInputs
    search: FocalSearchResult | None
    finished: Finished


@dataclass
class LensRoute:
    """What the lens-search route gave: the run on its warped tracks (None where not
    used), the refinement starts it spent, and the search (None where it did not run)."""

    warped: Warped | None
    spent: int
    search: LensSearchResult | None

    @property
    def bent(self) -> bool:
        """The search found the raw tracks clearly bent (a warp costs them much less,
        :attr:`.LensSearchResult.clear`)."""
        return self.search is not None and self.search.clear

    def finding(self) -> str | None:
        """The diagnosis where the tracks are bent and no warp was used, else None."""
        if self.search is None or not self.bent or self.warped is not None:
            return None
        return bent_tracks_finding(self.search)


NO_ROUTE = LensRoute(None, 0, None)


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
        data = camera_input(contents, camera, image_ids, options.start_options)
    read_clock = copy.deepcopy(clock)
    results: dict[str, CameraCalibration] = {}
    trifocal = [m for m in methods if m != "fundamental"]
    if trifocal:
        with clock("tracks"):
            tracks = select_camera_triplets(
                data, image_ids, options.track_options, options.work_options
            )
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
        results["fundamental"] = replace(
            results["fundamental"], timing=Timing(read_clock.total, read_clock.as_dict())
        )
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
    distortion, the lens search's warp (:mod:`.lens.warp`) and everything again on
    the warped tracks first."""
    inputs = AttemptInputs(data, tracks, estimator, method, options, clock)
    chosen = _chosen_run(inputs, first_start(data.prior, search), search)
    best = chosen.finished.attempt
    with clock("assessment"):
        result = assess(
            AssessInput(
                chosen.inputs.data,
                method,
                best.candidate,
                best.tensors.start,
                best.tensors.tensors,
                best.fallback,
                chosen.finished.polished,
                chosen.search,
                chosen.inputs.tracks.tracks,
                chosen.finished.lens,
                options.workers,
                chosen.finding,
                chosen.warped,
            )
        )
    result = replace(result, timing=Timing(clock.total, clock.as_dict(), estimator.starts_used))
    logger.info("camera %d: %s", data.camera.camera_id, clock.summary())
    return result


@dataclass
class _Chosen:
    """The run a method's result is assessed from: its inputs (raw or warped), its focal
    search, what it finished with, what the route found about the lens, and whether
    the estimate is the lens route's (warped tracks)."""

    inputs: AttemptInputs
    search: FocalSearchResult | None
    finished: Finished
    finding: str | None
    warped: bool = False


def _chosen_run(
    inputs: AttemptInputs, candidate: StartCandidate, search: FocalSearchResult | None
) -> _Chosen:
    """The lens route where it applies and its tensors agree, else the raw tracks'
    attempts from ``candidate`` and the other starts, finished (hold, polish, lens)."""
    lens_applies = lens_search_applies(inputs.data.camera, inputs.method, inputs.options)
    route = NO_ROUTE
    if lens_applies and first_tensors_disagree(inputs, candidate, inputs.options.search_triplets):
        # Most of the first triplets disagree: the lens search, before the other tensors.
        route = _through_lens_search(inputs)
    first = None
    if route.warped is None:
        # The restart waits for the lens search's verdict: on a lens it would refine
        # tensors the warp is about to replace.
        first = attempt(inputs, candidate, restart=False)
        if route.search is None and not first.majority_agrees and lens_applies:
            route = _through_lens_search(inputs)
    # One budget for the camera's tensor work, the warped tracks' included.
    inputs.estimator.charge(route.spent)
    if route.warped is not None:
        warped = route.warped
        return _Chosen(warped.inputs, warped.search, warped.finished, None, warped=True)
    assert first is not None
    best = restarted(inputs, first)
    if not route.bent:
        best = best_attempt(inputs, best, search)
    # Else the raw tracks are bent and no warp made the tensors agree: other focal
    # lengths cannot either (the disagreement is the lens's, not the start's). The lens
    # is named as the cause only where the raw tracks' tensors disagreed too.
    finding = None if first.majority_agrees else route.finding()
    return _Chosen(inputs, search, _finish(inputs, best), finding)


def _finish(
    inputs: AttemptInputs,
    best: Attempt,
    lens_start: Callable[[np.ndarray], LensStart] | None = None,
) -> Finished:
    """The estimate (every value held where nothing agrees), its polish and the lens
    stage; ``lens_start`` (the estimate -> raw tracks and a distortion to start from)
    where the tracks were warped, which the lens stage alone adjusts (no polish)."""
    camera, options, method = inputs.data.camera, inputs.options, inputs.method
    triplet_bundle = method == "msac-opt" and options.triplet_bundle
    if lens_start is not None and triplet_bundle and focal_held_against_most(best):
        finished = _focal_through_lens(inputs, best, lens_start)
        if finished is not None:
            return finished
    with inputs.clock("solve"):
        best = held_where_nothing_agrees(inputs, best)
        start, fallback = best.tensors.start, best.fallback
        estimate = checked_estimate(best, camera.camera_id, method)
    with inputs.clock("polish"):
        polished = Polished(
            estimate, fallback.relative_std, best.agreeing, None, fallback.free_parameters
        )
        if not triplet_bundle:
            return Finished(best, polished, None)
        if lens_start is None:
            # On warped tracks the lens stage adjusts K with the distortion from the
            # raw tracks: polishing K on the warped ones first would only move its start.
            polished = polish(
                PolishInput(
                    best.tensors.tensors,
                    inputs.tracks.by_images(),
                    start,
                    estimate,
                    fallback,
                    best.agreeing,
                    (camera.width, camera.height),
                    options.tau,
                    camera.camera_id,
                    options.workers,
                )
            )
        lens = _lens_stage(inputs, best, polished, lens_start)
    return Finished(best, polished, lens)


def _focal_through_lens(
    inputs: AttemptInputs, best: Attempt, lens_start: Callable[[np.ndarray], LensStart]
) -> Finished | None:
    """On warped tracks whose solve holds the focal length at the warp's focal search,
    which most tensors disagree with (:func:`.focal_held_against_most`): the lens stage
    with the focal length free from there, kept where it finds the distortion and at
    least half the tensors' triplets agree with its camera; else None (the value is then
    held at the start, :func:`.held_where_nothing_agrees`).

    Why. The warped tensors only approximate the lens (a one-parameter warp about the
    start's principal point), and on a near-planar scene the few pixels that leaves in
    the image corners make most of them disagree. The lens stage fits the camera's own
    model to the raw tracks, principal point included: its calibrated adjustment is the
    stronger test of a focal length (docs/lenses.md, "A focal length the warped tensors
    leave to a minority").
    """
    camera = inputs.data.camera
    freed = replace(best.fallback.free_parameters, focal="tied" if camera.single_focal else "free")
    with inputs.clock("solve"):
        estimate = checked_estimate(best, camera.camera_id, inputs.method)
    with inputs.clock("polish"):
        polished = Polished(estimate, best.fallback.relative_std, best.agreeing, None, freed)
        lens = _lens_stage(inputs, best, polished, lens_start)
    total = len(best.tensors.tensors)
    if lens is not None and not (lens.present and majority_of(lens.agreeing, total)):
        lens = None
    logger.info(
        "camera %d: %d of %d warped tensors agree with the lens search's focal length; "
        "the lens stage with f free: %s",
        camera.camera_id,
        best.agreeing,
        total,
        "not kept" if lens is None else f"{lens.agreeing} triplets agree, kept",
    )
    return None if lens is None else Finished(best, polished, lens)


def _lens_stage(
    inputs: AttemptInputs,
    best: Attempt,
    polished: Polished,
    lens_start: Callable[[np.ndarray], LensStart] | None,
) -> LensDistortion | None:
    """The lens stage (:func:`.estimate_distortion`) from the polished estimate, for what
    it estimates."""
    options = inputs.options
    return estimate_distortion(
        DistortionInput(
            best.tensors.tensors,
            inputs.tracks.by_images(),
            best.tensors.start,
            polished.intrinsics,
            polished.free_parameters,
            inputs.data.camera,
            options.tau,
            best.fallback.solution.inlier_tensors,
            options.workers,
            None if lens_start is None else lens_start(polished.intrinsics),
        )
    )


def _through_lens_search(raw: AttemptInputs) -> LensRoute:
    """The run on the lens search's warped tracks; its ``warped`` None where the search
    finds no clear warp, the tensors agree on none of its warps
    (:meth:`.LensSearchResult.candidates`), or the lens stage does not confirm the
    distortion.

    One start per warp: where its tensors do not agree, the next warp, then the
    unwarped run as it would have gone on. Where they agree, no second starts and no
    restart: the lens stage adjusts K from the raw tracks, so the warped tensors only
    choose its triplets and its start.

    The warps are centred on the start's principal point; where fewer than half the
    tensors agree on them, the warps about the image centre too
    (:func:`_about_image_centre`).
    """
    data, tracks, options = raw.data, raw.tracks, raw.options
    camera = data.camera
    with raw.clock("lens_search"):
        found = find_warp(data, tracks, options)
    if not found.clear:
        return LensRoute(None, 0, found)
    run, spent = _warped_attempt(raw, found, 0)
    if run is None or not run.best.majority_agrees:
        run, found, spent = _about_image_centre(raw, found, run, spent)
    if run is None:
        return LensRoute(None, spent, found)
    by_images = tracks.by_images()
    warp = run.warp
    finished = _finish(
        run.inputs,
        run.best,
        lambda intrinsics: LensStart(by_images, warp, intrinsics),
    )
    if finished.lens is None or not finished.lens.present:
        logger.info(
            "camera %d: the lens adjustment did not confirm the warp: not used", camera.camera_id
        )
        return LensRoute(None, spent, found)
    return LensRoute(Warped(run.inputs, warp.focal, finished), spent, found)


def _about_image_centre(
    raw: AttemptInputs, found: LensSearchResult, run: _WarpedAttempt | None, spent: int
) -> tuple[_WarpedAttempt | None, LensSearchResult, int]:
    """Where the warps about the start's principal point (``found``; ``run`` the attempt
    on them, None where no warp reached a consensus) leave most tensors disagreeing and
    that point is not the image centre (a prior's): the lens search again about the image
    centre, its warps tried with as much tensor work as the first ones took (``spent``),
    and its run kept where at least as many tensors agree on it. Returns the run and
    the search kept and the refinement starts spent.

    Why. A prior's principal point can be tens of pixels off (±5 %: 75 px across a
    3072-pixel image), where a lens's centre lies near the image centre; about the wrong
    centre a strong lens's tracks stay bent in the corners, and the best warp about it
    is not the lens's about the right one. A tie goes to the image centre, the better
    prior for a lens's centre (docs/lenses.md, "The warp's centre").
    """
    camera = raw.data.camera
    centre = default_guess(camera.width, camera.height)[2:]  # COLMAP's principal point
    if np.array_equal(centre, found.centre):
        return run, found, spent
    with raw.clock("lens_search"):
        about_centre = find_warp(raw.data, raw.tracks, raw.options, centre)
    centred = None
    if about_centre.clear:
        centred, spent = _warped_attempt(raw, about_centre, spent, allowance=spent)
    better = centred is not None and (run is None or centred.best.agreeing >= run.best.agreeing)
    logger.info(
        "camera %d: of %d triplets, %s agree on the tracks warped about the start's "
        "principal point, %s about the image centre (%s)",
        camera.camera_id,
        len(raw.tracks.triplets),
        "too few" if run is None else run.best.agreeing,
        "too few" if centred is None else centred.best.agreeing,
        "used" if better else "not used",
    )
    if centred is not None and better:
        return centred, about_centre, spent
    return run, found, spent


@dataclass
class _WarpedAttempt:
    """The attempt on tracks warped with ``warp`` whose tensors reached a consensus."""

    inputs: AttemptInputs
    best: Attempt
    warp: LensSearchResult


def _warped_attempt(
    raw: AttemptInputs, found: LensSearchResult, spent: int, allowance: int | None = None
) -> tuple[_WarpedAttempt | None, int]:
    """The first of the search's warps (:meth:`.LensSearchResult.candidates`) on whose
    tracks enough tensors agree (:func:`.consensus`), or None where none does, the
    camera's tensor budget runs out or this call has spent ``allowance`` refinement
    starts (None: no bound but the budget) before a warp; and the refinement starts
    spent, counted on from ``spent``."""
    data, tracks, options = raw.data, raw.tracks, raw.options
    camera = data.camera
    before = spent
    for family, parameter in found.candidates():
        if not raw.estimator.can_afford(spent + len(tracks.triplets)):
            return None, spent
        if allowance is not None and spent - before >= allowance:
            return None, spent
        warp = replace(found, family=family, parameter=parameter)
        warped_data, warped_tracks = warped_input(data, tracks, warp)
        estimator = TensorEstimator(warped_tracks, camera.camera_id, options, raw.estimator.seeds)
        inputs = replace(raw, data=warped_data, tracks=warped_tracks, estimator=estimator)
        best = attempt(inputs, first_start(data.prior, warp.focal), restart=False, complete=False)
        if not consensus(best.fallback):
            best = restarted(inputs, best)
        spent += estimator.starts_used
        if consensus(best.fallback):
            return _WarpedAttempt(inputs, best, warp), spent
        logger.info(
            "camera %d: %d of %d tensors agree on the tracks warped with %s",
            camera.camera_id,
            best.agreeing,
            len(best.tensors.tensors),
            warp.describe(),
        )
    return None, spent
