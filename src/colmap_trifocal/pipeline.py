"""Calibrate every camera of a COLMAP database: the public entry point.

``calibrate_database(path, options)`` reads the database (never changing it),
then for each camera: undistorts its keypoints with the stored distortion,
selects triplets of images taken with that camera, estimates one robust tensor
per triplet, and solves for (fx, fy, cx, cy) with the chosen method. With
``options.write`` the estimates are stored in the database (backup first, one
transaction).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .cameras import CameraInfo, check_supported, undistort_to_pinhole
from .database import DatabaseContents, read_database, write_intrinsics
from .errors import CalibrationError
from .focal_search import search_focal
from .fundamental import calibrate_from_fundamentals
from .log import logger
from .parallel import map_jobs
from .selfcalibration import MSAC_TAU, solve, theta_to_intrinsics
from .tensor_estimation import TensorEstimationOptions, TripletTensor, estimate_triplet_tensor
from .tracks import MatchGraph, Triplet, select_triplets
from .trifocal import intrinsics_matrix

METHODS = ("msac-opt", "msac", "direct", "fundamental")
PARAMETER_NAMES = ("fx", "fy", "cx", "cy")
#: A parameter counts as observable when its standard deviation is below this
#: fraction of the focal length (2 %: well beyond the ±5 % of a typical prior).
OBSERVABLE_RELATIVE_STD = 0.02
#: See ``CalibrationOptions.restart``. A safety net for gross offsets only: measured
#: on the Strecha scenes, after the focal search, priors 10–30 % off per parameter
#: give the same accuracy without the re-estimation (0.147 / 0.158 % vs 0.158 / 0.162 %).
RESTART_THRESHOLD = 0.15


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
    #: Cameras to calibrate; None: all cameras with at least 3 images.
    camera_ids: list[int] | None = None
    seed: int = 0
    #: Triplets used per camera (the ones with most tracks). Measured on the Strecha
    #: scenes (±5 % priors, 10 seeds): 20 triplets are as accurate as 30 (fountain
    #: 0.152 vs 0.153 %, Herz-Jesus 0.122 vs 0.150 %) and 30 % faster.
    max_triplets: int = 20
    min_tracks: int = 40
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
    #: Triplets (those with most tracks) the focal search uses.
    search_triplets: int = 6
    #: Re-estimate the tensors once from the estimate when it lies more than
    #: ``RESTART_THRESHOLD`` (relative to the focal length) from the start
    #: (msac and msac-opt; ``direct`` has no outlier defence, so its far-off
    #: estimates come from bad tensors, not from the start).
    restart: bool = True


@dataclass
class CameraCalibration:
    """The estimate for one camera, as written by ``calibrate --json``."""

    camera_id: int
    model: str
    method: str
    fx: float
    fy: float
    cx: float
    cy: float
    std: dict[str, float | None]
    observable: dict[str, bool]
    num_triplets: int
    num_inlier_triplets: int
    seconds: float
    prior: tuple[float, float, float, float]
    #: (fx, fy, cx, cy) the tensors were normalised with: the prior after the focal
    #: search (and after the re-estimation when the estimate moved far from it).
    start: tuple[float, float, float, float]
    tensors: list[TripletTensor] = field(default_factory=list, repr=False)

    @property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy) in pixels."""
        return np.array([self.fx, self.fy, self.cx, self.cy])

    def to_json(self) -> dict:
        """The JSON object of DESIGN.md (plus the prior used)."""
        data = asdict(self)
        data.pop("tensors")
        data["prior"] = dict(zip(PARAMETER_NAMES, self.prior, strict=True))
        data["start"] = dict(zip(PARAMETER_NAMES, self.start, strict=True))
        return data


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
    if options.no_prior and options.prior is not None:
        raise CalibrationError("--prior and --no-prior exclude each other")
    if options.method not in METHODS:
        raise CalibrationError(f"unknown method {options.method!r} (choose from {METHODS})")
    path = Path(path)
    contents = read_database(path)
    results = calibrate_contents(contents, options)
    if options.write:
        updated = {
            r.camera_id: contents.cameras[r.camera_id].with_intrinsics(r.fx, r.fy, r.cx, r.cy)
            for r in results
        }
        backup = write_intrinsics(path, updated)
        logger.info("wrote %d camera(s) to %s (backup: %s)", len(updated), path, backup)
    return results


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
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise CalibrationError(f"unknown method {unknown[0]!r} (choose from {METHODS})")
    images_of: dict[int, list[int]] = {}
    for image_id, camera_id in contents.image_camera.items():
        images_of.setdefault(camera_id, []).append(image_id)
    if options.camera_ids is not None:
        missing = sorted(set(options.camera_ids) - set(contents.cameras))
        if missing:
            raise CalibrationError(f"camera id {missing[0]} is not in the database")
        camera_ids = sorted(options.camera_ids)
    else:
        camera_ids = sorted(c for c in contents.cameras if len(images_of.get(c, [])) >= 3)
        if not camera_ids:
            raise CalibrationError("no camera has at least 3 images")
    results: dict[str, list[CameraCalibration]] = {m: [] for m in methods}
    for c in camera_ids:
        per_method = calibrate_camera(
            contents, contents.cameras[c], sorted(images_of.get(c, [])), options, methods
        )
        for method, result in per_method.items():
            results[method].append(result)
    return results


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


def calibrate_camera(
    contents: DatabaseContents,
    camera: CameraInfo,
    image_ids: list[int],
    options: CalibrationOptions,
    methods: tuple[str, ...],
) -> dict[str, CameraCalibration]:
    """Estimate one camera from the triplets of its own images, with each of ``methods``."""
    check_supported(camera)
    if len(image_ids) < 3:
        raise CalibrationError(
            f"camera {camera.camera_id} has {len(image_ids)} image(s); at least 3 are needed"
        )
    if options.no_prior:
        prior = default_guess(camera.width, camera.height)
    elif options.prior is not None:
        prior = np.asarray(options.prior, float)
    else:
        prior = np.asarray(camera.intrinsics, float)
    if camera.single_focal:
        prior[:2] = prior[:2].mean()
    keypoints = {i: undistort_to_pinhole(camera, contents.keypoints[i]) for i in image_ids}
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
    if options.focal_search:
        found = search_focal(
            tracks[: options.search_triplets],
            data.prior,
            np.random.default_rng(seeds[-1]),
            options.tensor.inlier_threshold_px,
            workers=options.workers,
            progress=options.progress,
        )
        start[:2] = found.focal
        logger.info("camera %d: focal search: %.1f px", camera.camera_id, found.focal)
    tensors = _estimate_tensors(triplets, tracks, start, seeds[:-1], camera, options)
    return _PreparedTensors(
        triplets, tracks, seeds[:-1], start, tensors, time.perf_counter() - clock
    )


def _solve_camera(
    data: _CameraInput, prepared: _PreparedTensors, method: str, options: CalibrationOptions
) -> CameraCalibration:
    """One trifocal variant on the prepared tensors (re-estimated once if it moves far)."""
    clock = time.perf_counter()
    camera = data.camera
    start, tensors = prepared.start, prepared.tensors
    solution = solve(tensors, method, camera.single_focal, options.tau)
    estimate = theta_to_intrinsics(solution.theta, start)
    if options.restart and method != "direct" and _moved(estimate, start):
        logger.info(
            "camera %d: estimate far from the start; re-estimating the tensors", camera.camera_id
        )
        start = estimate
        tensors = _estimate_tensors(
            prepared.triplets, prepared.tracks, start, prepared.seeds, camera, options
        )
        solution = solve(tensors, method, camera.single_focal, options.tau)
        estimate = theta_to_intrinsics(solution.theta, start)
    agree = int(solution.inlier_tensors.sum())
    if not (np.all(np.isfinite(estimate)) and min(estimate[:2]) > 0 and agree > 0):
        raise CalibrationError(
            f"camera {camera.camera_id}: no valid estimate (fx {estimate[0]:.4g}, fy "
            f"{estimate[1]:.4g}; {agree} of {len(tensors)} tensors agree): too little "
            "parallax or wrong matches"
        )
    scale = np.array([start[0], start[1], start[0], start[1]])
    std = np.sqrt(np.maximum(np.diag(solution.covariance), 0.0)) * scale
    return CameraCalibration(
        camera_id=camera.camera_id,
        model=camera.model,
        method=method,
        **dict(zip(PARAMETER_NAMES, map(float, estimate), strict=True)),
        std={name: float(s) for name, s in zip(PARAMETER_NAMES, std, strict=True)},
        observable=_observable(std, data.prior),
        num_triplets=len(tensors),
        num_inlier_triplets=int(solution.inlier_tensors.sum()),
        seconds=prepared.seconds + time.perf_counter() - clock,
        prior=tuple(map(float, data.prior)),  # type: ignore[arg-type]
        start=tuple(map(float, start)),  # type: ignore[arg-type]
        tensors=tensors,
    )


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


def _observable(std: np.ndarray, prior: np.ndarray) -> dict[str, bool]:
    focal = float(np.mean(prior[:2]))
    return {
        name: bool(np.isfinite(s) and s < OBSERVABLE_RELATIVE_STD * focal)
        for name, s in zip(PARAMETER_NAMES, std, strict=True)
    }


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
    )
