"""Settings of a calibration and the checks of its inputs (prior, stored camera).

:class:`CalibrationOptions` mirrors the ``calibrate`` flags; priors are (fx, fy, cx, cy)
in pixels, COLMAP's pixel convention (centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from numbers import Integral, Real

import numpy as np

from ..common.errors import CalibrationError
from ..database.camera_groups import GROUPINGS
from ..database.cameras import (
    PINHOLE_MODELS,
    CameraInfo,
)
from ..geometry.tensor_estimation import (
    TensorEstimationOptions,
)
from .solve.constraints import MSAC_TAU

METHODS = ("msac-opt", "msac", "direct", "fundamental")


#: See ``CalibrationOptions.restart``: an estimate this far (relative) from the start
#: has its tensors estimated again from it. Tensors normalised by a start whose
#: principal point is far off turn into outliers and leave it undetermined, while
#: the unconstrained estimate is already close (docs/accuracy.md).
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
    #: every triplet with enough tracks. More cost time without making the estimate
    #: better (docs/accuracy.md, ``benchmarks/triplet_sampling.py``).
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
    #: hypotheses (:mod:`intrinsics.start.focal_search`) before estimating the tensors.
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
    #: msac-opt only: polish the estimate by a bundle adjustment of the agreeing
    #: triplets' tracks with one shared camera (:mod:`intrinsics.polish.bundle`), kept when at
    #: least as many triplets agree with it and its image jackknife is no wider than
    #: the constraint solve's. Near-planar triplets, whose whitened
    #: constraints are a poor first-order measure, then count by their likelihood.
    triplet_bundle: bool = True

    def __post_init__(self) -> None:
        """Refuse values the calibration cannot use, here rather than deep inside it.

        Raises:
            CalibrationError: one line naming the option (its ``calibrate`` flag).
        """
        check_option_values(self)


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
    return values


def check_camera_values(camera: CameraInfo, *, uses_stored: bool) -> None:
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


#: Seeds of the calibration go to numpy's SeedSequence (64-bit words are plenty; the
#: command line keeps to ``common.arguments.MAX_SEED`` because mapping passes it to COLMAP).
MAX_SEED = 2**64 - 1


def _is_integer(value: object) -> bool:
    """An integer that is not a bool (numpy integers included)."""
    return isinstance(value, Integral) and not isinstance(value, bool)


#: The options that are True or False (a string such as "no" is refused, not taken as True).
BOOLEAN_OPTIONS = ("no_prior", "write", "progress", "focal_search", "restart", "triplet_bundle")


def check_option_values(options: CalibrationOptions) -> None:
    """CalibrationError for a value of the wrong type or outside its range.

    The prior is normalised to a tuple of four floats (a list or an array is taken).
    """
    if not isinstance(options.method, str) or options.method not in METHODS:
        raise CalibrationError(f"unknown method {options.method!r} (choose from {METHODS})")
    if not isinstance(options.group, str) or options.group not in GROUPINGS:
        raise CalibrationError(f"unknown --group {options.group!r} (choose from {GROUPINGS})")
    for name in BOOLEAN_OPTIONS:
        value = getattr(options, name)
        if not isinstance(value, bool | np.bool_):
            raise CalibrationError(f"{name} must be True or False, got {value!r}")
    if options.sequence is not None and not isinstance(options.sequence, bool | np.bool_):
        raise CalibrationError(f"sequence must be True, False or None, got {options.sequence!r}")
    if not _is_integer(options.seed) or not 0 <= int(options.seed) <= MAX_SEED:
        raise CalibrationError(
            f"--seed must be an integer in [0, {MAX_SEED}], got {options.seed!r}"
        )
    if options.prior is not None:
        values = options.prior
        if isinstance(values, str | bytes) or not hasattr(values, "__len__") or len(values) != 4:
            raise CalibrationError(
                f"--prior must be four numbers (fx, fy, cx, cy), got {options.prior!r}"
            )
        try:
            prior = tuple(float(v) for v in values)
        except (TypeError, ValueError):
            raise CalibrationError(
                f"--prior must be four numbers (fx, fy, cx, cy), got {options.prior!r}"
            ) from None
        if not all(math.isfinite(v) for v in prior) or prior[0] <= 0 or prior[1] <= 0:
            raise CalibrationError(
                f"--prior {prior}: values must be finite and focal lengths positive"
            )
        options.prior = prior  # type: ignore[assignment]
    if options.camera_ids is not None and (
        isinstance(options.camera_ids, str | bytes)
        or not hasattr(options.camera_ids, "__iter__")
        or not all(_is_integer(c) for c in options.camera_ids)
    ):
        raise CalibrationError(
            f"--camera-id: a list of integer camera ids, got {options.camera_ids!r}"
        )
    if options.max_triplets is not None and (
        not _is_integer(options.max_triplets) or options.max_triplets < 1
    ):
        raise CalibrationError("--max-triplets must be at least 1")
    for name, value, low in (
        ("min_tracks", options.min_tracks, 7),
        ("search_triplets", options.search_triplets, 1),
    ):
        if not _is_integer(value) or value < low:
            raise CalibrationError(f"{name} must be an integer of at least {low}, got {value!r}")
    if options.workers is not None and (not _is_integer(options.workers) or options.workers < 1):
        raise CalibrationError(
            f"workers must be a positive integer or None, got {options.workers!r}"
        )
    if not (isinstance(options.tau, Real) and math.isfinite(options.tau) and options.tau > 0):
        raise CalibrationError(f"tau must be a finite number above 0, got {options.tau!r}")


def check_options(options: CalibrationOptions) -> None:
    """CalibrationError for a value of the wrong type (checked again here: the options may
    have changed since they were made) or options that exclude each other."""
    check_option_values(options)
    if options.no_prior and options.prior is not None:
        raise CalibrationError("--prior and --no-prior exclude each other")


def start_source(camera: CameraInfo, options: CalibrationOptions) -> str:
    """Where the starting intrinsics of ``camera`` come from (``START_SOURCES``)."""
    if options.prior is not None:
        return "--prior"
    if options.no_prior:
        return "default guess"
    return "EXIF focal length" if camera.has_prior_focal_length else "stored camera"
