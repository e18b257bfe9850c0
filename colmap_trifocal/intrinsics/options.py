"""Settings of a calibration, by the stage that reads them, checked once when made.

:class:`CalibrationOptions` mirrors the ``calibrate`` flags and keeps their flat names
(``CalibrationOptions(prior=..., seed=...)``); it is frozen, and refuses a value the
calibration cannot use when it is made. Each stage reads its own part: where the
tensors start (:class:`StartOptions`), which triplets (:class:`TrackOptions`), how
they are solved (:class:`SolveOptions`), and how the work runs (:class:`WorkOptions`).
Priors are (fx, fy, cx, cy) in pixels, COLMAP's pixel convention (centre of the
top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from numbers import Integral, Real
from typing import Literal, get_args

import numpy as np

from ..common.errors import CalibrationError
from ..database.camera_groups import GROUPINGS
from ..geometry.tensor_estimation import TensorEstimationOptions
from .solve.constraints import MSAC_TAU

#: The variants: TrifocalCalib's three and the Mendonça–Cipolla baseline.
Method = Literal["msac-opt", "msac", "direct", "fundamental"]
METHODS: tuple[Method, ...] = get_args(Method)

#: See ``CalibrationOptions.restart``: an estimate this far (relative) from the start
#: has its tensors estimated again from it. Tensors normalised by a start whose
#: principal point is far off turn into outliers and leave it undetermined, while
#: the unconstrained estimate is already close (docs/accuracy.md).
RESTART_THRESHOLD = 0.05

#: Three-view tracks a triplet needs (``TrackOptions.min_tracks`` None)...
DEFAULT_MIN_TRACKS = 40
#: ... and on a sparse capture, where fewer triplets than wanted have that many: as many
#: as a tensor needs inliers (``TensorEstimationOptions.min_inliers``).
SPARSE_MIN_TRACKS = 30

#: Seeds of the calibration go to numpy's SeedSequence (64-bit words are plenty; the
#: command line keeps to ``common.arguments.MAX_SEED`` because mapping passes it to COLMAP).
MAX_SEED = 2**64 - 1

Prior = tuple[float, float, float, float]


def _is_integer(value: object) -> bool:
    """An integer that is not a bool (numpy integers included)."""
    return isinstance(value, Integral) and not isinstance(value, bool)


def _check_booleans(owner: object, *names: str) -> None:
    """CalibrationError unless each named option is True or False (a string such as
    ``"no"`` is refused, not taken as True)."""
    for name in names:
        value = getattr(owner, name)
        if not isinstance(value, bool | np.bool_):
            raise CalibrationError(f"{name} must be True or False, got {value!r}")


def _checked_prior(values: object) -> Prior:
    """Four finite numbers with positive focal lengths, as floats."""
    if isinstance(values, str | bytes) or not hasattr(values, "__len__") or len(values) != 4:
        raise CalibrationError(f"--prior must be four numbers (fx, fy, cx, cy), got {values!r}")
    try:
        prior = tuple(float(v) for v in values)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise CalibrationError(
            f"--prior must be four numbers (fx, fy, cx, cy), got {values!r}"
        ) from None
    if not all(math.isfinite(v) for v in prior) or prior[0] <= 0 or prior[1] <= 0:
        raise CalibrationError(f"--prior {prior}: values must be finite and focal lengths positive")
    return (prior[0], prior[1], prior[2], prior[3])


@dataclass(frozen=True)
class StartOptions:
    """Where a camera's tensors start from.

    Attributes:
        prior: (fx, fy, cx, cy) in pixels for every camera; None: the stored camera.
        no_prior: start from COLMAP's guess for the image size instead of the stored
            camera (f = 1.2 · max(width, height), centred principal point).
        focal_search: replace the start's focal length by a search over calibrated
            three-view hypotheses (:mod:`intrinsics.start.focal_search`) where the
            tracks favour it.
        search_triplets: triplets the focal search (and the lens search) use: the first
            selected ones.
    """

    prior: Prior | None = None
    no_prior: bool = False
    focal_search: bool = True
    search_triplets: int = 6

    def __post_init__(self) -> None:
        _check_booleans(self, "no_prior", "focal_search")
        if self.prior is not None:
            object.__setattr__(self, "prior", _checked_prior(self.prior))
        if self.no_prior and self.prior is not None:
            raise CalibrationError("--prior and --no-prior exclude each other")
        if not _is_integer(self.search_triplets) or self.search_triplets < 1:
            raise CalibrationError(
                f"search_triplets must be an integer of at least 1, got {self.search_triplets!r}"
            )


@dataclass(frozen=True)
class TrackOptions:
    """Which triplets a camera is calibrated from.

    Attributes:
        max_triplets: triplets per camera, spread over the view graph
            (:mod:`colmap_trifocal.geometry.tracks`); None: every triplet with enough
            tracks. More cost time without making the estimate better.
        min_tracks: three-view tracks a triplet needs; None: ``DEFAULT_MIN_TRACKS``, or
            where fewer than ``max_triplets`` triplets have that many (a sparse capture)
            ``SPARSE_MIN_TRACKS``, so that more of the images are used.
        sequence: choose triplets for a sequence (video, driving): over wider frame
            gaps and across turns; None: where the view graph is one and the camera
            moves forward.
    """

    max_triplets: int | None = 20
    min_tracks: int | None = None
    sequence: bool | None = None

    def __post_init__(self) -> None:
        if self.max_triplets is not None and (
            not _is_integer(self.max_triplets) or self.max_triplets < 1
        ):
            raise CalibrationError("--max-triplets must be at least 1")
        if self.min_tracks is not None and (
            not _is_integer(self.min_tracks) or self.min_tracks < 7
        ):
            raise CalibrationError(
                f"min_tracks must be an integer of at least 7, got {self.min_tracks!r}"
            )
        if self.sequence is not None and not isinstance(self.sequence, bool | np.bool_):
            raise CalibrationError(f"sequence must be True, False or None, got {self.sequence!r}")


@dataclass(frozen=True)
class SolveOptions:
    """How a camera's tensors are estimated and solved.

    Attributes:
        method: the TrifocalCalib variant (``msac-opt``, ``msac``, ``direct``) or the
            Mendonça–Cipolla baseline (``fundamental``).
        tau: the MSAC threshold on the whitened constraint norm.
        tensor: the per-triplet estimation's settings.
        restart: re-estimate the tensors once from the estimate where it lies more than
            ``RESTART_THRESHOLD`` (relative to the focal length) from the start (msac and
            msac-opt: ``direct`` has no outlier defence, so its far-off estimates come
            from bad tensors, not from the start).
        triplet_bundle: msac-opt only: polish the estimate by a bundle adjustment of the
            agreeing triplets' tracks with one shared camera
            (:mod:`intrinsics.polish.bundle`), kept where it is at least as well
            supported as the constraint estimate.
    """

    method: Method = "msac-opt"
    tau: float = MSAC_TAU
    tensor: TensorEstimationOptions = field(default_factory=TensorEstimationOptions)
    restart: bool = True
    triplet_bundle: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.method, str) or self.method not in METHODS:
            raise CalibrationError(f"unknown method {self.method!r} (choose from {METHODS})")
        _check_booleans(self, "restart", "triplet_bundle")
        if not (isinstance(self.tau, Real) and math.isfinite(self.tau) and self.tau > 0):
            raise CalibrationError(f"tau must be a finite number above 0, got {self.tau!r}")
        if not isinstance(self.tensor, TensorEstimationOptions):
            raise CalibrationError(
                f"tensor must be a TensorEstimationOptions, got {type(self.tensor).__name__}"
            )


@dataclass(frozen=True)
class WorkOptions:
    """How the work runs: its seed, its processes, its progress bar.

    Attributes:
        seed: the random seed; the same seed gives the same result bit for bit.
        workers: parallel workers (None: one per core, at most 8; 1: all the work in
            the calling thread): forked processes fit the triplets' tensors where that
            is safe, threads do the rest (:func:`..common.parallel.map_jobs`). Every
            triplet has its own seed, so the result does not depend on this.
        progress: show progress bars (stderr).
    """

    seed: int = 0
    workers: int | None = None
    progress: bool = False

    def __post_init__(self) -> None:
        _check_booleans(self, "progress")
        if not _is_integer(self.seed) or not 0 <= int(self.seed) <= MAX_SEED:
            raise CalibrationError(
                f"--seed must be an integer in [0, {MAX_SEED}], got {self.seed!r}"
            )
        if self.workers is not None and (not _is_integer(self.workers) or self.workers < 1):
            raise CalibrationError(
                f"workers must be a positive integer or None, got {self.workers!r}"
            )


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate_database` (the CLI flags of ``calibrate``), by their
    flat names; the stages read their parts (``start_options``, ``track_options``,
    ``solve_options``, ``work_options``). Frozen: change one with
    ``dataclasses.replace(options, seed=1)``, which checks it again.

    ``camera_ids`` selects cameras (each its whole group; None: every group), ``group``
    how camera ids are grouped into physical cameras (``auto``: same model, size and
    stored parameters; ``camera``: one per id; ``all``: one camera), ``write`` stores
    the estimates in the database. The rest: the parts' attributes.
    """

    method: Method = "msac-opt"
    prior: Prior | None = None
    no_prior: bool = False
    camera_ids: tuple[int, ...] | None = None
    group: str = "auto"
    seed: int = 0
    max_triplets: int | None = 20
    min_tracks: int | None = None
    sequence: bool | None = None
    tau: float = MSAC_TAU
    tensor: TensorEstimationOptions = field(default_factory=TensorEstimationOptions)
    write: bool = False
    progress: bool = False
    workers: int | None = None
    focal_search: bool = True
    search_triplets: int = 6
    restart: bool = True
    triplet_bundle: bool = True
    start_options: StartOptions = field(init=False, repr=False, compare=False)
    track_options: TrackOptions = field(init=False, repr=False, compare=False)
    solve_options: SolveOptions = field(init=False, repr=False, compare=False)
    work_options: WorkOptions = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Refuse values the calibration cannot use, here rather than deep inside it.

        Raises:
            CalibrationError: one line naming the option (its ``calibrate`` flag).
        """
        solve = SolveOptions(self.method, self.tau, self.tensor, self.restart, self.triplet_bundle)
        if not isinstance(self.group, str) or self.group not in GROUPINGS:
            raise CalibrationError(f"unknown --group {self.group!r} (choose from {GROUPINGS})")
        _check_booleans(self, "write")
        work = WorkOptions(self.seed, self.workers, self.progress)
        start = StartOptions(self.prior, self.no_prior, self.focal_search, self.search_triplets)
        object.__setattr__(self, "prior", start.prior)
        if self.camera_ids is not None:
            object.__setattr__(self, "camera_ids", _checked_camera_ids(self.camera_ids))
        tracks = TrackOptions(self.max_triplets, self.min_tracks, self.sequence)
        for name, part in (
            ("start_options", start),
            ("track_options", tracks),
            ("solve_options", solve),
            ("work_options", work),
        ):
            object.__setattr__(self, name, part)


def _checked_camera_ids(values: object) -> tuple[int, ...]:
    """At least one integer camera id (any iterable of them), as a tuple."""
    if isinstance(values, str | bytes) or not isinstance(values, Iterable):
        raise CalibrationError(f"--camera-id: a list of integer camera ids, got {values!r}")
    ids = tuple(values)
    if not ids or not all(_is_integer(c) for c in ids):
        raise CalibrationError(
            f"--camera-id: a list of integer camera ids (at least one), got {values!r}"
        )
    return tuple(int(c) for c in ids)


def check_options(options: object) -> CalibrationOptions:
    """``options`` if it is a :class:`CalibrationOptions` (checked when it was made, and
    frozen since); CalibrationError otherwise."""
    if not isinstance(options, CalibrationOptions):
        raise CalibrationError(
            f"options must be a CalibrationOptions, got {type(options).__name__}"
        )
    return options
