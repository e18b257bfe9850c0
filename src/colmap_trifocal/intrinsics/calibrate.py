"""Calibrate every camera of a COLMAP database: the public entry point.

``calibrate_database(path, options)`` reads the database (never changing it),
groups its camera ids into physical cameras (:mod:`..database.camera_groups`;
COLMAP's default gives one camera id per image), then for each group with at
least 3 images: undistorts each image's keypoints with its own camera's stored
distortion, selects triplets among the group's images, estimates one robust
tensor per triplet, and solves for (fx, fy, cx, cy) with the chosen method.
Groups with fewer images are skipped (reported, not an error, while another
group calibrates). With ``options.write`` the estimates are stored in every
camera of each group (backup first, one transaction).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..common.errors import CalibrationError
from ..common.log import logger
from ..common.parallel import map_jobs
from ..database.camera_groups import GROUPINGS, CameraGroup, group_cameras
from ..database.cameras import (
    PINHOLE_MODELS,
    CameraInfo,
    check_supported,
    undistort_to_pinhole,
)
from ..database.snapshot import DatabaseContents, read_database, write_intrinsics
from ..geometry.tensor_estimation import (
    TensorEstimationOptions,
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
from .diagnosis import diagnose
from .focal_search import FocalSearchResult, search_focal
from .fundamental import calibrate_from_fundamentals
from .group_results import GroupCalibration, SkippedGroup
from .observability import FALLBACK_FACTOR, default_held_std, tolerance
from .parametrization import FULL, SINGLE_FOCAL
from .results import PARAMETER_NAMES, CameraCalibration, TripletReport, finite_or_none
from .selfcalibration import (
    MSAC_TAU,
    FallbackSolution,
    SelfCalibrationResult,
    fold_focal_sign,
    solve_with_fallback,
    theta_to_intrinsics,
)

METHODS = ("msac-opt", "msac", "direct", "fundamental")
#: See ``CalibrationOptions.restart``. Tensors normalised by a start whose principal
#: point is 10 % of f off (a 28 % prior on fountain-P11's cy) were half outliers
#: (10 of 20 MSAC inliers), which left cy undetermined; the unconstrained estimate
#: was still within 0.5 %, and re-estimating from it restored 19–20 inliers.
RESTART_THRESHOLD = 0.05


@dataclass
class CalibrationOptions:
    """Settings of :func:`calibrate_database` (the CLI flags of ``calibrate``)."""

    method: str = "msac-opt"
    #: Starting point (fx, fy, cx, cy) in pixels for every camera; None: the stored camera.
    prior: tuple[float, float, float, float] | None = None
    #: Ignore the stored camera and start from COLMAP's guess for the image size
    #: (f = 1.2 · max(width, height), centred principal point); the focal search
    #: does the rest.
    no_prior: bool = False
    #: Cameras to calibrate (each selects its whole group); None: every group.
    camera_ids: list[int] | None = None
    #: How camera ids are grouped into physical cameras: ``auto`` (same model, size
    #: and stored parameters), ``camera`` (one per camera id) or ``all`` (one camera).
    group: str = "auto"
    seed: int = 0
    #: Triplets used per camera, spread over the view graph (:mod:`.tracks`); None:
    #: every triplet with enough tracks. Measured on the Strecha scenes (±5 % priors,
    #: 10 seeds): 20 triplets are as accurate as 30 (fountain 0.152 vs 0.153 %,
    #: Herz-Jesus 0.122 vs 0.150 %) and 30 % faster; see also
    #: ``benchmarks/triplet_sampling.py``.
    max_triplets: int | None = 20
    min_tracks: int = 40
    #: Choose triplets for a sequence (video, driving): over wider frame gaps and
    #: across turns, by :func:`.tracks.information_score` rather than track count.
    #: None: when the view graph is one (:func:`.tracks.is_sequence`).
    sequence: bool | None = None
    tau: float = MSAC_TAU
    tensor: TensorEstimationOptions = field(default_factory=TensorEstimationOptions)
    write: bool = False
    progress: bool = False
    #: Processes estimating triplet tensors (None: one per core, at most 8).
    #: Every triplet has its own seed, so the result does not depend on this.
    workers: int | None = None
    #: Replace the prior's focal length by a search over calibrated three-view
    #: hypotheses (:mod:`.focal_search`) before estimating the tensors.
    focal_search: bool = True
    #: Triplets the focal search uses (the first selected ones: the one with most
    #: tracks, then the best-matched of the rest spread over the images).
    search_triplets: int = 6
    #: Re-estimate the tensors once from the estimate when it lies more than
    #: ``RESTART_THRESHOLD`` (relative to the focal length) from the start, using
    #: the unconstrained estimate of the parameters it roughly determines
    #: (:func:`_restart_point`; msac and msac-opt: ``direct`` has no outlier
    #: defence, so its far-off estimates come from bad tensors, not from the start).
    restart: bool = True


#: Starting focal lengths, as multiples of the image's larger side (see check_prior).
PRIOR_FOCAL_RANGE = (0.01, 100.0)
#: Largest distance of a starting principal point from the image centre, in image sizes.
PRIOR_PRINCIPAL_POINT_RANGE = 1.5


def parse_prior(text: str) -> tuple[float, float, float, float]:
    """Parse ``FX,FY,CX,CY`` (pixels); CalibrationError on anything else."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise CalibrationError(
            f"malformed --prior {text!r}: expected four numbers FX,FY,CX,CY"
        ) from None
    if len(values) != 4:
        raise CalibrationError(
            f"malformed --prior {text!r}: expected 4 values FX,FY,CX,CY, got {len(values)}"
        )
    if not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise CalibrationError(
            f"invalid --prior {text!r}: values must be finite and focal lengths positive"
        )
    return values  # type: ignore[return-value]


def check_camera_values(camera: CameraInfo, uses_stored: bool) -> None:
    """Refuse a camera whose stored values the calibration cannot start from.

    The image size must be positive. The stored params must be finite with positive
    focal lengths when they are used: as the prior (``uses_stored``) or to undistort the
    keypoints (any model with distortion parameters).
    """
    if camera.width < 1 or camera.height < 1:
        raise CalibrationError(
            f"camera {camera.camera_id} has an image size of {camera.width}x{camera.height} "
            "pixels (corrupt database?)"
        )
    if not uses_stored and camera.model in PINHOLE_MODELS:
        return
    fx, fy, _, _ = camera.intrinsics
    if not np.all(np.isfinite(camera.params)) or not (fx > 0 and fy > 0):
        values = ", ".join(f"{v:.6g}" for v in camera.params)
        raise CalibrationError(
            f"camera {camera.camera_id}: the stored params ({values}) are not usable "
            "(not finite, or a focal length <= 0)"
            + ("; give --prior or --no-prior" if camera.model in PINHOLE_MODELS else "")
        )


def check_prior(prior: np.ndarray, camera: CameraInfo, source: str) -> None:
    """Refuse starting intrinsics (fx, fy, cx, cy; pixels) that no camera of this size has.

    Focal lengths must lie within ``PRIOR_FOCAL_RANGE`` times the image's larger side
    (0.01: a field of view far beyond 180°; 100: below 0.6°) and the principal point
    within ``PRIOR_PRINCIPAL_POINT_RANGE`` image sizes of the image centre. Outside,
    the arithmetic overflows or loses all precision long before a tensor is estimated.
    """
    side = float(max(camera.width, camera.height))
    low, high = PRIOR_FOCAL_RANGE[0] * side, PRIOR_FOCAL_RANGE[1] * side
    fx, fy, cx, cy = (float(v) for v in prior)
    size = np.array([camera.width, camera.height], float)
    offset = np.abs(np.array([cx, cy]) - size / 2) / size
    if not (
        np.all(np.isfinite(prior))
        and low <= fx <= high
        and low <= fy <= high
        and np.all(offset <= PRIOR_PRINCIPAL_POINT_RANGE)
    ):
        raise CalibrationError(
            f"camera {camera.camera_id}: invalid starting intrinsics from {source}: "
            f"fx = {fx:.6g}, fy = {fy:.6g}, cx = {cx:.6g}, cy = {cy:.6g} px; for a "
            f"{camera.width}x{camera.height} image the focal lengths must lie in "
            f"[{low:.6g}, {high:.6g}] px and the principal point within "
            f"{PRIOR_PRINCIPAL_POINT_RANGE:g} image sizes of the centre"
        )


def default_guess(width: int, height: int) -> np.ndarray:
    """COLMAP's starting intrinsics for an image size: f = 1.2 · max(w, h), centred (pixels)."""
    focal = 1.2 * max(width, height)
    return np.array([focal, focal, width / 2.0, height / 2.0])


def calibrate_database(
    path: Path | str, options: CalibrationOptions | None = None
) -> list[CameraCalibration]:
    """Estimate the intrinsics of the cameras of a COLMAP database.

    Args:
        path: the database; opened read-only unless ``options.write``.
        options: method, prior, seed, ... (defaults: msac-opt from the stored cameras).

    Returns:
        One result per calibrated camera, ordered by camera id.

    Raises:
        CalibrationError: bad input (see the message).
    """
    options = options or CalibrationOptions()
    check_options(options)
    path = Path(path)
    contents = read_database(path)
    results = calibrate_contents(contents, options)
    if options.write:
        write_calibrations(path, results)
    return results


def check_options(options: CalibrationOptions) -> None:
    """CalibrationError for options that exclude each other or unknown choices."""
    if options.no_prior and options.prior is not None:
        raise CalibrationError("--prior and --no-prior exclude each other")
    if options.method not in METHODS:
        raise CalibrationError(f"unknown method {options.method!r} (choose from {METHODS})")
    if options.group not in GROUPINGS:
        raise CalibrationError(f"unknown --group {options.group!r} (choose from {GROUPINGS})")


def updated_cameras(
    results: list[CameraCalibration], determined_only: bool = True
) -> dict[int, CameraInfo]:
    """camera_id -> stored camera with its group's estimate, for every camera of every group.

    Distortion is kept per camera. With ``determined_only`` a group the images
    determined nothing of is left out (writing the prior back would record a guess).
    """
    updated: dict[int, CameraInfo] = {}
    for r in results:
        if determined_only and not r.determined_anything:
            continue
        if isinstance(r, GroupCalibration):
            updated.update(r.updated_cameras())
        elif r.stored_camera is not None:
            updated[r.camera_id] = r.stored_camera.with_intrinsics(r.fx, r.fy, r.cx, r.cy)
    return updated


def write_calibrations(path: Path | str, results: list[CameraCalibration]) -> int:
    """Store the estimates in the database at ``path`` (backup first, one transaction).

    Every camera id of a group gets the group's estimate. A group the images
    determined nothing of keeps its stored parameters: writing the prior back
    would record a guess as a calibration. Distortion is kept, per camera.

    Returns:
        The number of cameras written.

    Raises:
        CalibrationError: see :func:`.database.write_intrinsics`.
    """
    updated = updated_cameras(results)
    if updated:
        backup = write_intrinsics(Path(path), updated)
        logger.info("wrote %d camera(s) to %s (backup: %s)", len(updated), path, backup)
    return len(updated)


def calibrate_contents(
    contents: DatabaseContents, options: CalibrationOptions
) -> list[CameraCalibration]:
    """Calibrate the cameras of already-read database contents (see :func:`calibrate_database`)."""
    return calibrate_contents_methods(contents, options, (options.method,))[options.method]


def calibrate_contents_methods(
    contents: DatabaseContents, options: CalibrationOptions, methods: tuple[str, ...]
) -> dict[str, list[CameraCalibration]]:
    """Several methods on the same contents; the trifocal variants share one set of tensors.

    Each result's ``seconds`` is what that method alone would take (the shared
    focal search and tensors plus its own solve). ``options.method`` is ignored.
    Results are :class:`.group_results.GroupCalibration` (one per calibrated group);
    skipped groups are only logged here (see :func:`calibrate_groups`).
    """
    return calibrate_groups(contents, options, methods)[0]


def plan_groups(
    contents: DatabaseContents, options: CalibrationOptions
) -> tuple[list[CameraGroup], list[SkippedGroup]]:
    """The groups to calibrate (``options.group``, ``options.camera_ids``), and those skipped.

    A group with fewer than 3 images is skipped. Raises CalibrationError for an
    unknown camera id, and when no group has 3 images.
    """
    groups = group_cameras(
        contents.cameras, contents.image_camera, options.group, contents.rig_sensor_cameras
    )
    if options.camera_ids is not None:
        missing = sorted(set(options.camera_ids) - set(contents.cameras))
        if missing:
            raise CalibrationError(f"camera id {missing[0]} is not in the database")
        wanted = set(options.camera_ids)
        groups = [g for g in groups if wanted & set(g.camera_ids)]
        if not groups:
            raise CalibrationError(f"camera {min(wanted)} has no images")
    ready = [g for g in groups if len(g.image_ids) >= 3]
    skipped = [
        SkippedGroup(list(g.camera_ids), len(g.image_ids), _images(len(g.image_ids)))
        for g in groups
        if len(g.image_ids) < 3
    ]
    if not ready:
        if options.camera_ids is not None and len(groups) == 1:
            (group,) = groups
            raise CalibrationError(
                f"{group.describe()} has {_images(len(group.image_ids))}; at least 3 are needed"
            )
        raise CalibrationError(
            "no camera has at least 3 images (grouped with --group "
            f"{options.group}: {len(groups)} group(s) of at most "
            f"{max((len(g.image_ids) for g in groups), default=0)} image(s))"
        )
    return ready, skipped


def _images(count: int) -> str:
    """``1 image``, ``2 images``."""
    return f"{count} image" if count == 1 else f"{count} images"


def calibrate_groups(
    contents: DatabaseContents, options: CalibrationOptions, methods: tuple[str, ...]
) -> tuple[dict[str, list[GroupCalibration]], list[SkippedGroup]]:
    """Calibrate every group with each of ``methods``; also return the skipped groups.

    With several groups, one that cannot be calibrated (no triplet, no valid
    estimate, ...) is skipped with the reason while the others calibrate; when none
    calibrates, the first group's error is raised.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise CalibrationError(f"unknown method {unknown[0]!r} (choose from {METHODS})")
    groups, skipped = plan_groups(contents, options)
    results: dict[str, list[GroupCalibration]] = {m: [] for m in methods}
    first_error: CalibrationError | None = None
    for group in groups:
        cameras = [contents.cameras[c] for c in group.camera_ids]
        if len(group.camera_ids) > 1:
            logger.info(
                "%s: %d images with shared intrinsics", group.describe(), len(group.image_ids)
            )
        try:
            per_method = calibrate_camera(
                contents, cameras[0], list(group.image_ids), options, methods
            )
        except CalibrationError as exc:
            if len(groups) == 1:
                raise
            first_error = first_error or exc
            logger.warning("%s skipped: %s", group.describe(), exc)
            skipped.append(SkippedGroup(list(group.camera_ids), len(group.image_ids), str(exc)))
            continue
        source = start_source(cameras[0], options)
        for method, result in per_method.items():
            results[method].append(GroupCalibration.of(result, cameras, source))
    if not results[methods[0]] and first_error is not None:
        raise first_error
    for group in skipped:
        logger.warning("%s", group.message())
    skipped.sort(key=lambda g: g.camera_id)
    return results, skipped


def start_source(camera: CameraInfo, options: CalibrationOptions) -> str:
    """Where the starting intrinsics of ``camera`` come from (``START_SOURCES``)."""
    if options.prior is not None:
        return "--prior"
    if options.no_prior:
        return "default guess"
    return "EXIF focal length" if camera.has_prior_focal_length else "stored camera"


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
        sequence = is_sequence(graph, image_ids)
    if sequence:
        logger.info("camera %d: a sequence: triplets over wide gaps and turns", camera.camera_id)
        motions = pair_motions(data.matches, data.keypoints)
        triplets = select_sequence_triplets(
            graph, image_ids, motions, options.min_tracks, options.max_triplets or 100
        )
    else:
        triplets = select_triplets(graph, image_ids, options.min_tracks, options.max_triplets)
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
    aspect = np.sqrt(held[1] / held[0])
    held[:2] = search.focal / aspect, search.focal * aspect
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

    def solve_from(start: np.ndarray, tensors: list[TripletTensor]) -> FallbackSolution:
        tolerances = tolerance(start, camera.width, camera.height)
        return solve_with_fallback(
            tensors, method, base, start, held, tolerances, options.tau, held_std
        )

    start, tensors = prepared.start, prepared.tensors
    fallback = solve_from(start, tensors)
    restart = _restart_point(fallback, start)
    if options.restart and method != "direct" and _moved(restart, start):
        logger.info(
            "camera %d: estimate far from the start; re-estimating the tensors", camera.camera_id
        )
        start = restart
        tensors = _estimate_tensors(
            prepared.triplets, prepared.tracks, start, prepared.seeds, camera, options
        )
        fallback = solve_from(start, tensors)
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
    estimated = model.estimated(camera.single_focal)
    # Determined: estimated, std within tolerance (held values' uncertainty counted)
    # and actually moved by the data (:func:`.selfcalibration.data_moves`).
    within = (fallback.relative_std < fallback.tolerances) & fallback.moved
    observable = {
        name: estimated[name] and bool(ok) for name, ok in zip(PARAMETER_NAMES, within, strict=True)
    }
    focal_scale = np.array([start[0], start[1], start[0], start[1]])
    std = fallback.relative_std * focal_scale
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
        unconstrained_std={
            name: finite_or_none(s) for name, s in zip(PARAMETER_NAMES, unconstrained, strict=True)
        },
        triplets=_triplet_reports(tensors, solution, start),
        tensors=tensors,
        stored_camera=camera,
    )


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
