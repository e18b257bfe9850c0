"""One physical camera: triplets, focal search, tensors, and the solve for K.

:func:`calibrate_camera` takes a group's images (keypoints undistorted with each
image's own camera), selects triplets (sequences over wide gaps), searches the focal
length, estimates one tensor per triplet from that start and solves the 15 constraints
with each method; parameters the tracks do not determine are tied or held at the best
evidence (:func:`held_values`). Intrinsics in pixels, COLMAP's pixel convention.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..common.errors import CalibrationError
from ..common.log import logger
from ..common.parallel import map_jobs
from ..database.cameras import (
    CameraInfo,
    check_supported,
    undistort_to_pinhole,
)
from ..database.snapshot import DatabaseContents
from ..geometry.tensor_estimation import (
    TripletTensor,
    estimate_triplet_tensor,
)
from ..geometry.tracks import (
    MatchGraph,
    Triplet,
    is_sequence,
    pair_motions,
    select_sequence_triplets,
    select_triplets,
)
from ..geometry.trifocal import intrinsics_matrix
from .diagnosis import diagnose, moves_forward
from .focal_search import FocalSearchResult, search_focal
from .fundamental import calibrate_from_fundamentals
from .observability import FALLBACK_FACTOR, default_held_std, tolerance
from .options import (
    RESTART_THRESHOLD,
    CalibrationOptions,
    check_camera_values,
    check_prior,
    default_guess,
    start_source,
)
from .parametrization import FULL, SINGLE_FOCAL
from .results import PARAMETER_NAMES, CameraCalibration, TripletReport, finite_or_none
from .selfcalibration import (
    CalibrationProblem,
    FallbackSolution,
    SelfCalibrationResult,
    fold_focal_sign,
    solve_with_fallback,
    theta_to_intrinsics,
)
from .triplet_bundle import TripletBundleResult, polish_intrinsics, pycolmap_camera_setup
from .uncertainty import jackknife_covariance


@dataclass
class _CameraInput:
    """One camera's undistorted keypoints, matches and prior (shared by all methods)."""

    camera: CameraInfo
    prior: np.ndarray
    keypoints: dict[int, np.ndarray]
    matches: dict[tuple[int, int], np.ndarray]


@dataclass
class _PreparedTensors:
    """Triplets, their tracks and seeds, the start K and the tensors estimated from it."""

    triplets: list[Triplet]
    tracks: list[np.ndarray]
    seeds: list[np.random.SeedSequence]
    start: np.ndarray
    tensors: list[TripletTensor]
    seconds: float
    #: The focal search's outcome (None: not run).
    search: FocalSearchResult | None = None


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
    """
    check_supported(camera)
    if len(image_ids) < 3:
        raise CalibrationError(
            f"camera {camera.camera_id} has {len(image_ids)} image(s); at least 3 are needed"
        )
    source = start_source(camera, options)
    if source == "EXIF focal length":
        checked = " (checked by the focal search)" if options.focal_search else ""
        logger.info(
            "camera %d: starting from the EXIF focal length %.1f px%s",
            camera.camera_id,
            camera.intrinsics[0],
            checked,
        )
    check_camera_values(camera, uses_stored=options.prior is None and not options.no_prior)
    if options.no_prior:
        prior = default_guess(camera.width, camera.height)
        prior_origin = "--no-prior"
    elif options.prior is not None:
        prior = np.asarray(options.prior, float)
        prior_origin = "--prior"
    else:
        prior = np.asarray(camera.intrinsics, float)
        prior_origin = "the stored camera (give --prior or --no-prior)"
    if camera.single_focal:
        prior[:2] = prior[:2].mean()
    check_prior(prior, camera, prior_origin)
    own_camera = {
        i: contents.cameras.get(contents.image_camera.get(i, -1), camera) for i in image_ids
    }
    keypoints = {i: undistort_to_pinhole(own_camera[i], contents.keypoints[i]) for i in image_ids}
    own = set(image_ids)
    matches = {p: m for p, m in contents.matches.items() if p[0] in own and p[1] in own}
    if not matches:
        raise CalibrationError(f"camera {camera.camera_id}: no verified matches between its images")
    data = _CameraInput(camera, prior, keypoints, matches)
    results: dict[str, CameraCalibration] = {}
    prepared: _PreparedTensors | None = None
    for method in methods:
        if method == "fundamental":
            results[method] = _fundamental(data, time.perf_counter())
            continue
        if prepared is None:
            prepared = _prepare_tensors(data, image_ids, options)
        results[method] = _solve_camera(data, prepared, method, options)
    return results


def _prepare_tensors(
    data: _CameraInput, image_ids: list[int], options: CalibrationOptions
) -> _PreparedTensors:
    """Triplet selection, the focal search and one tensor per triplet."""
    clock = time.perf_counter()
    camera = data.camera
    graph = MatchGraph(data.matches, {i: len(k) for i, k in data.keypoints.items()})
    sequence = options.sequence
    if sequence is None:
        sequence = is_sequence(graph, image_ids) and moves_forward(
            data.keypoints, data.matches, data.prior
        )
    if sequence:
        logger.info("camera %d: a sequence: triplets over wide gaps and turns", camera.camera_id)
        motions = pair_motions(data.matches, data.keypoints)
        triplets = select_sequence_triplets(
            graph, image_ids, motions, options.min_tracks, options.max_triplets or 100
        )
    else:
        triplets = select_triplets(
            graph, image_ids, options.min_tracks, options.max_triplets, keypoints=data.keypoints
        )
    if not triplets:
        raise CalibrationError(
            f"camera {camera.camera_id}: no image triplet with at least {options.min_tracks} "
            "three-view tracks"
        )
    tracks = [
        np.stack(
            [
                data.keypoints[i][triplet.keypoint_indices[:, v]]
                for v, i in enumerate(triplet.image_ids)
            ]
        )
        for triplet in triplets
    ]
    seeds = np.random.SeedSequence(options.seed).spawn(len(triplets) + 1)
    start = data.prior.copy()
    found = None
    if options.focal_search:
        found = search_focal(
            tracks[: options.search_triplets],
            data.prior,
            np.random.default_rng(seeds[-1]),
            options.tensor.inlier_threshold_px,
            workers=options.workers,
            progress=options.progress,
            image_size=(camera.width, camera.height),
        )
        if found.improves_on_start:
            start[:2] = found.focal
        logger.info(
            "camera %d: focal search: %.1f px (std %.1f %%, %s, %s)",
            camera.camera_id,
            found.focal,
            100 * found.relative_std,
            "decisive" if found.decisive else "not decisive",
            "used" if found.improves_on_start else "the start explains the tracks as well: kept",
        )
    tensors = _estimate_tensors(triplets, tracks, start, seeds[:-1], camera, options)
    return _PreparedTensors(
        triplets, tracks, seeds[:-1], start, tensors, time.perf_counter() - clock, found
    )


def held_values(
    prior: np.ndarray, search: FocalSearchResult | None
) -> tuple[np.ndarray, np.ndarray, str]:
    """What undetermined parameters are held at: the best estimate the run has.

    The focal search's focal length when the tracks favour it over the prior
    (:attr:`.FocalSearchResult.improves_on_start`; the prior's aspect ratio kept),
    else the prior's. The principal point is always the prior's.

    Returns:
        (fx, fy, cx, cy) in pixels, their std relative to the focal length (θ
        units; a prior's assumed :func:`.observability.default_held_std`), and the
        source of the focal length (``"focal-search"`` or ``"prior"``).
    """
    held = np.asarray(prior, float).copy()
    std = default_held_std()
    if search is None or not search.improves_on_start:
        return held, std, "prior"
    held[:2] = _with_focal(held, search.focal)[:2]
    std[:2] = search.relative_std
    return held, std, "focal-search"


def _solve_camera(
    data: _CameraInput, prepared: _PreparedTensors, method: str, options: CalibrationOptions
) -> CameraCalibration:
    """One trifocal variant on the prepared tensors (re-estimated once if it moves far).

    Parameters the triplets do not determine are tied (fy = fx) or held at the
    prior (:func:`.selfcalibration.solve_with_fallback`).
    """
    clock = time.perf_counter()
    camera = data.camera
    base = SINGLE_FOCAL if camera.single_focal else FULL

    held, held_std, held_source = held_values(data.prior, prepared.search)

    def solve_from(
        start: np.ndarray, tensors: list[TripletTensor], held: np.ndarray, held_std: np.ndarray
    ) -> FallbackSolution:
        tolerances = tolerance(start, camera.width, camera.height)
        problem = CalibrationProblem(
            tensors, method, start, held, tolerances, options.tau, held_std
        )
        return solve_with_fallback(problem, base)

    def solve_and_restart(
        start: np.ndarray, tensors: list[TripletTensor], held: np.ndarray, held_std: np.ndarray
    ) -> tuple[np.ndarray, list[TripletTensor], FallbackSolution]:
        fallback = solve_from(start, tensors, held, held_std)
        restart = _restart_point(fallback, start)
        if options.restart and method != "direct" and _moved(restart, start):
            logger.info(
                "camera %d: estimate far from the start; re-estimating the tensors",
                camera.camera_id,
            )
            start = restart
            tensors = _estimate_tensors(
                prepared.triplets, prepared.tracks, start, prepared.seeds, camera, options
            )
            fallback = solve_from(start, tensors, held, held_std)
        return start, tensors, fallback

    start, tensors, fallback = solve_and_restart(prepared.start, prepared.tensors, held, held_std)
    for other_start in _other_starts(prepared.search, start, method, options):
        if 2 * _agreeing(fallback) >= len(fallback.solution.inlier_tensors):
            break
        logger.info(
            "camera %d: %d of %d tensors agree; estimating them again from f = %.1f px "
            "(focal search)",
            camera.camera_id,
            _agreeing(fallback),
            len(fallback.solution.inlier_tensors),
            other_start[0],
        )
        # Held (if the focal length stays undetermined) at this start, known no better
        # than a prior: the search's cost did not single it out.
        other_held = np.r_[other_start[:2], data.prior[2:]]
        other_std = default_held_std()
        other_tensors = _estimate_tensors(
            prepared.triplets, prepared.tracks, other_start, prepared.seeds, camera, options
        )
        other = solve_and_restart(other_start, other_tensors, other_held, other_std)
        if _agreeing(other[2]) > _agreeing(fallback):
            start, tensors, fallback = other
            held, held_std, held_source = other_held, other_std, "focal-search"
    estimate = fold_focal_sign(theta_to_intrinsics(fallback.solution.theta, start))
    solution, model = fallback.solution, fallback.model
    # An estimate no tensor agrees with is garbage (e.g. copies of one image with
    # jitter); direct (no outlier defence) and a result held at the prior are exempt.
    agree = int(solution.inlier_tensors.sum())
    checked = method != "direct" and model.dimension > 0
    if not (np.all(np.isfinite(estimate)) and min(estimate[:2]) > 0 and (agree or not checked)):
        raise CalibrationError(
            f"camera {camera.camera_id}: no valid estimate (fx {estimate[0]:.4g}, fy "
            f"{estimate[1]:.4g}; {agree} of {len(tensors)} tensors agree): too little "
            "parallax or wrong matches"
        )
    if model != base:
        logger.info("camera %d: assumed %s", camera.camera_id, "; ".join(model.assumptions()))
    focal_scale = np.array([start[0], start[1], start[0], start[1]])
    relative = fallback.relative_std
    polish = None
    if method == "msac-opt" and options.triplet_bundle:
        estimate, relative, agree, polish = _polished(
            data, prepared, tensors, start, estimate, fallback, agree, options.tau
        )
    estimated = model.estimated(camera.single_focal)
    # Determined: estimated, std within tolerance (held values' uncertainty counted)
    # and actually moved by the data (:func:`.selfcalibration.data_moves`).
    within = (relative < fallback.tolerances) & fallback.moved
    observable = {
        name: estimated[name] and bool(ok) for name, ok in zip(PARAMETER_NAMES, within, strict=True)
    }
    std = relative * focal_scale
    unconstrained = fallback.unconstrained.relative_std * focal_scale
    source = parameter_sources(estimated, model, held_source)
    diagnosis = None if all(observable.values()) else diagnose(prepared.tracks, estimate)
    reported_std = {
        name: finite_or_none(s) if estimated[name] else None
        for name, s in zip(PARAMETER_NAMES, std, strict=True)
    }
    for index, name in enumerate(PARAMETER_NAMES):
        if source[name] == "focal-search":
            reported_std[name] = float(held_std[index] * held[index])
    return CameraCalibration(
        camera_id=camera.camera_id,
        model=camera.model,
        method=method,
        **dict(zip(PARAMETER_NAMES, map(float, estimate), strict=True)),
        std=reported_std,
        observable=observable,
        num_triplets=len(tensors),
        num_inlier_triplets=agree,
        seconds=prepared.seconds + time.perf_counter() - clock,
        prior=tuple(map(float, data.prior)),  # type: ignore[arg-type]
        start=tuple(map(float, start)),  # type: ignore[arg-type]
        assumptions=[
            note.replace("the prior", _SOURCE_WORDS[held_source], 1)
            if note.startswith("fx, fy")
            else note
            for note in model.assumptions()
        ],
        estimated=estimated,
        source=source,
        focal_search=_search_summary(prepared.search),
        diagnosis=diagnosis,
        triplet_bundle=polish,
        unconstrained_std={
            name: finite_or_none(s) for name, s in zip(PARAMETER_NAMES, unconstrained, strict=True)
        },
        triplets=_triplet_reports(tensors, solution, start),
        tensors=tensors,
        stored_camera=camera,
    )


def _polished(
    data: _CameraInput,
    prepared: _PreparedTensors,
    tensors: list[TripletTensor],
    start: np.ndarray,
    estimate: np.ndarray,
    fallback: FallbackSolution,
    agree: int,
    tau: float,
) -> tuple[np.ndarray, np.ndarray, int, dict | None]:
    """The estimate, its relative std, the agreeing tensors and a summary after the polish.

    The bundle adjustment of the agreeing triplets (:mod:`.triplet_bundle`) replaces
    the constraint estimate when

    * at least as many triplets agree with it (λ < τ²) as tensors did (‖r‖ < τ), and
    * its image jackknife spreads no more than the constraint solve's (the sum of the
      estimated parameters' jackknife variances, relative to the focal length; both
      over the same image groups). Measured: on the synthetic straight drive, where
      the focal length is barely determined, the polish's jackknife std of fx was
      1.6 % against the constraints' 0.6 %, and its error 1.0 % against 0.5 %.

    Its std is the larger of the constraint solve's (which counts held and tied
    values' uncertainty) and the polish's own jackknife spread. Otherwise everything
    is returned unchanged.
    """
    model, relative_std = fallback.model, fallback.relative_std
    if pycolmap_camera_setup(model) is None:
        return estimate, relative_std, agree, None
    camera = data.camera
    tracks = {
        tuple(triplet.image_ids): x
        for triplet, x in zip(prepared.triplets, prepared.tracks, strict=True)
    }
    polished = polish_intrinsics(
        tensors, tracks, start, estimate, model, (camera.width, camera.height), tau
    )
    summary = {
        "used": False,
        "agreeing": None if polished is None else int(polished.agreeing.sum()),
        "constraints": dict(zip(PARAMETER_NAMES, map(float, estimate), strict=True)),
    }
    focal_scale = np.array([start[0], start[1], start[0], start[1]])
    spread = None if polished is None else polished.jackknife_std()
    why = _polish_rejected(polished, spread, focal_scale, fallback, agree)
    if why:
        logger.info(
            "camera %d: bundle adjustment of the triplets not kept: %s", camera.camera_id, why
        )
        summary["rejected"] = why
        return estimate, relative_std, agree, summary
    summary["used"] = True
    if spread is not None:
        relative_std = np.maximum(relative_std, spread / focal_scale)
    logger.info(
        "camera %d: bundle adjustment of %d agreeing triplets: fx %.2f, fy %.2f, cx %.2f, "
        "cy %.2f px",
        camera.camera_id,
        int(polished.agreeing.sum()),
        *polished.intrinsics,
    )
    return polished.intrinsics, relative_std, int(polished.agreeing.sum()), summary


def _polish_rejected(
    polished: TripletBundleResult | None,
    spread: np.ndarray | None,
    focal_scale: np.ndarray,
    fallback: FallbackSolution,
    agree: int,
) -> str | None:
    """Why the polish is not kept (see :func:`_polished`), or None."""
    if polished is None:
        return "it failed"
    if int(polished.agreeing.sum()) < agree:
        return (
            f"{int(polished.agreeing.sum())} triplets agree with it, {agree} with the constraints"
        )
    replicates = fallback.solution.jackknife
    if spread is None or replicates is None:
        return None
    estimated = fallback.model.parametrization(np.ones(4), np.ones(4)).matrix.any(axis=1)
    polish_variance = float(np.sum((spread / focal_scale)[estimated] ** 2))
    constraint_variance = float(np.sum(np.diag(jackknife_covariance(replicates))[estimated]))
    if polish_variance > constraint_variance:
        return (
            f"its jackknife spread ({np.sqrt(polish_variance):.2%}) exceeds the constraints' "
            f"({np.sqrt(constraint_variance):.2%})"
        )
    return None


_SOURCE_WORDS = {"prior": "the prior", "focal-search": "the focal search's estimate"}


def parameter_sources(estimated: dict[str, bool], model, held_source: str) -> dict[str, str]:
    """Where each reported value comes from: ``trifocal`` (estimated from the
    constraints), ``tied`` (fy = fx, square pixels assumed), ``focal-search`` or
    ``prior`` (held)."""
    source = {}
    for name in PARAMETER_NAMES:
        if estimated[name]:
            source[name] = "trifocal"
        elif name == "fy" and model.focal == "tied":
            source[name] = "tied"
        elif name in ("fx", "fy"):
            source[name] = held_source
        else:
            source[name] = "prior"
    return source


def _search_summary(search: FocalSearchResult | None) -> dict | None:
    """The focal search's result for the JSON report (pixels; None if not run)."""
    if search is None:
        return None
    return {
        "focal": float(search.focal),
        "std": float(search.relative_std * search.focal),
        "decisive": bool(search.decisive),
        "used": bool(search.improves_on_start),
    }


def _triplet_reports(
    tensors: list[TripletTensor], solution: SelfCalibrationResult, start: np.ndarray
) -> list[TripletReport]:
    """Per-tensor diagnostics of a solve (candidates and scores for msac / msac-opt)."""
    reports = []
    for index, tensor in enumerate(tensors):
        candidate = score = None
        if solution.per_tensor_theta is not None and solution.per_tensor_scores is not None:
            intrinsics = fold_focal_sign(
                theta_to_intrinsics(solution.per_tensor_theta[index], start)
            )
            candidate = tuple(map(float, intrinsics))
            score = float(solution.per_tensor_scores[index])
        reports.append(
            TripletReport(
                image_ids=tuple(int(i) for i in tensor.image_ids),  # type: ignore[arg-type]
                num_tracks=tensor.num_tracks,
                num_inliers=tensor.num_inliers,
                sigma_px=float(tensor.sigma_px),
                residual_norm=float(solution.norms[index]),
                inlier=bool(solution.inlier_tensors[index]),
                candidate=candidate,  # type: ignore[arg-type]
                score=score,
            )
        )
    return reports


def _estimate_tensors(
    triplets: list[Triplet],
    tracks: list[np.ndarray],
    start: np.ndarray,
    seeds: list[np.random.SeedSequence],
    camera: CameraInfo,
    options: CalibrationOptions,
) -> list[TripletTensor]:
    """One tensor per triplet (in parallel) in coordinates normalised by ``start``."""
    K0 = intrinsics_matrix(start)
    jobs = [
        (triplet.image_ids, x, K0, seed, options.tensor)
        for triplet, x, seed in zip(triplets, tracks, seeds, strict=True)
    ]
    estimated = map_jobs(
        _estimate_job,
        jobs,
        options.workers,
        f"camera {camera.camera_id}: tensors",
        options.progress,
    )
    tensors = [t for t in estimated if t is not None]
    logger.info(
        "camera %d: %d of %d triplets gave a tensor", camera.camera_id, len(tensors), len(triplets)
    )
    if len(tensors) < 1:
        raise CalibrationError(
            f"camera {camera.camera_id}: no triplet gave a consistent trifocal tensor"
        )
    return tensors


def _restart_point(fallback: FallbackSolution, start: np.ndarray) -> np.ndarray:
    """Where to re-estimate the tensors from: the unconstrained estimate, where trusted.

    Parameters whose unconstrained std exceeds ``FALLBACK_FACTOR`` tolerances keep
    their start value; an untrusted focal length follows the trusted one with the
    start's aspect ratio (planar motion leaves fy wandering tens of percent away).
    """
    unconstrained = fallback.unconstrained
    estimate = fold_focal_sign(theta_to_intrinsics(unconstrained.theta, start))
    trusted = unconstrained.relative_std < FALLBACK_FACTOR * fallback.tolerances
    point = np.where(trusted, estimate, start)
    if trusted[0] and not trusted[1]:
        point[1] = point[0] * start[1] / start[0]
    elif trusted[1] and not trusted[0]:
        point[0] = point[1] * start[0] / start[1]
    return point


def _agreeing(fallback: FallbackSolution) -> int:
    """Tensors that agree with (are MSAC inliers at) a solve's estimate."""
    return int(fallback.solution.inlier_tensors.sum())


#: Other starts :func:`_other_starts` offers at most (besides the first).
MAX_OTHER_STARTS = 3


def _other_starts(
    search: FocalSearchResult | None,
    start: np.ndarray,
    method: str,
    options: CalibrationOptions,
) -> list[np.ndarray]:
    """Other starts when the tracks reject the first: the focal search's candidates.

    When fewer than half the tensors agree with the estimate from ``start`` (the
    tensors, estimated in coordinates normalised by a wrong K, are far from any
    calibrated one: on an 11° turntable from COLMAP's default camera, 0 of 20
    agreed), the tensors are estimated again from the focal search's focal length,
    then from the other local minima of its coarse cost curve (lowest cost first;
    the weak perspective of a narrow lens can put the global minimum 3× off), each
    more than ``RESTART_THRESHOLD`` from the focal lengths tried before, at most
    ``MAX_OTHER_STARTS``. The caller tries them only while fewer than half the
    tensors agree, keeps the start with most agreeing tensors and stops at the first
    that half of them agree with.
    """
    if search is None or not options.restart or method == "direct":
        return []
    tried = [float(np.sqrt(start[0] * start[1]))]
    starts = []
    for focal in [search.focal, *search.local_minima()]:
        if all(abs(focal / f - 1.0) > RESTART_THRESHOLD for f in tried):
            tried.append(focal)
            starts.append(_with_focal(start, focal))
    return starts[:MAX_OTHER_STARTS]


def _with_focal(intrinsics: np.ndarray, focal: float) -> np.ndarray:
    """(fx, fy, cx, cy) with √(fx·fy) set to ``focal`` (pixels), the aspect ratio and the
    principal point of ``intrinsics`` kept."""
    aspect = np.sqrt(intrinsics[1] / intrinsics[0])
    return np.array([focal / aspect, focal * aspect, intrinsics[2], intrinsics[3]])


def _moved(estimate: np.ndarray, start: np.ndarray) -> bool:
    """Whether any parameter moved more than RESTART_THRESHOLD of the focal length."""
    focal = np.array([start[0], start[1], start[0], start[1]])
    return bool(np.max(np.abs(estimate - start) / focal) > RESTART_THRESHOLD)


def _estimate_job(job: tuple) -> TripletTensor | None:
    """One triplet's tensor; its own seed makes results independent of scheduling."""
    image_ids, tracks, K0, seed, tensor_options = job
    return estimate_triplet_tensor(
        image_ids, tracks, K0, np.random.default_rng(seed), tensor_options
    )


def _fundamental(data: _CameraInput, start: float) -> CameraCalibration:
    """The Mendonça–Cipolla baseline on F re-estimated from the undistorted verified matches.

    F is re-fitted (normalised 8-point on COLMAP's inliers) rather than read from
    the database because the stored F relates raw, distorted keypoints.
    """
    camera, prior, keypoints = data.camera, data.prior, data.keypoints
    fundamentals, weights = [], []
    for (a, b), m in data.matches.items():
        if len(m) < 15:
            continue
        F, _ = cv2.findFundamentalMat(keypoints[a][m[:, 0]], keypoints[b][m[:, 1]], cv2.FM_8POINT)
        if F is not None and F.shape == (3, 3):
            fundamentals.append(F)
            weights.append(len(m))
    if len(fundamentals) < 2:
        raise CalibrationError(
            f"camera {camera.camera_id}: fewer than 2 image pairs with enough verified matches"
        )
    result = calibrate_from_fundamentals(
        np.stack(fundamentals), prior, np.asarray(weights, float), camera.single_focal
    )
    nan = {name: None for name in PARAMETER_NAMES}
    return CameraCalibration(
        camera_id=camera.camera_id,
        model=camera.model,
        method="fundamental",
        **dict(zip(PARAMETER_NAMES, map(float, result.intrinsics), strict=True)),
        std=nan,
        observable={name: bool(result.success) for name in PARAMETER_NAMES},
        num_triplets=0,
        num_inlier_triplets=0,
        seconds=time.perf_counter() - start,
        prior=tuple(map(float, prior)),  # type: ignore[arg-type]
        start=tuple(map(float, prior)),  # type: ignore[arg-type]
        stored_camera=camera,
    )
