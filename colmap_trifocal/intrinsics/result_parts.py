"""The parts of a camera's result (:class:`.results.CameraCalibration`): each triplet's
report, the timing, the diagnostics, the provenance, and the keys of its JSON form.

Units: intrinsics in pixels (COLMAP's pixel convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..database.cameras import CameraInfo
from ..geometry.tensor_estimation import TripletTensor

#: What :func:`intrinsics.assess.diagnosis.diagnose` says when the tracks show no known cause.
NO_CAUSE = "no degenerate motion found"

#: ``start_source`` values: where the starting intrinsics came from.
START_SOURCES = ("--prior", "default guess", "EXIF focal length", "stored camera")


@dataclass
class TripletReport:
    """One image triplet's tensor and how the constraints judged it.

    Attributes:
        image_ids: database ids of views 1, 2, 3.
        num_tracks: three-view tracks of the triplet.
        num_inliers: tracks consistent with the refined tensor.
        sigma_px: keypoint noise estimated by the triplet's bundle adjustment, px.
        residual_norm: whitened constraint norm ‖r‖ at the final estimate
            (≈ sqrt(χ²(7)) for a good tensor at the true K).
        inlier: ``residual_norm`` below the MSAC threshold τ.
        candidate: (fx, fy, cx, cy) this tensor alone gives (msac, msac-opt), px.
        score: MSAC score of ``candidate`` over all tensors (1 perfect, 0 none).
    """

    image_ids: tuple[int, int, int]
    num_tracks: int
    num_inliers: int
    sigma_px: float
    residual_norm: float
    inlier: bool
    candidate: tuple[float, float, float, float] | None = None
    score: float | None = None


@dataclass(frozen=True)
class Timing:
    """What a camera's calibration cost.

    Attributes:
        seconds: wall seconds in all (= ``stage_seconds["total"]``).
        stage_seconds: wall seconds of each stage (read, tracks, focal_search, tensors,
            solve, lens_search, polish, assessment) and their ``total``; shared stages
            count for every method calibrated together.
        tensor_starts: triplet refinement starts the tensors stage ran for this camera
            (its work; bounded by
            :data:`intrinsics.tensors.estimator.MAX_STARTS_PER_TRIPLET` per triplet).
    """

    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    tensor_starts: int = 0


@dataclass(frozen=True)
class Diagnostics:
    """How the estimate came about, stage by stage.

    Attributes:
        focal_search: the focal search's result: focal length and std (pixels), whether
            its cost curve was decisive and whether it replaced the prior's focal length.
        diagnosis: the cause of undetermined parameters the data shows
            (:mod:`intrinsics.assess.diagnosis`), or None.
        triplet_bundle: msac-opt's bundle adjustment of the agreeing triplets
            (:mod:`intrinsics.polish.bundle`): ``used`` (it replaced the constraint
            estimate), ``agreeing`` triplets (λ < τ²; None when it failed) and the
            constraint estimate it started from (``constraints``: fx, fy, cx, cy in
            pixels); where the constraint solve held the principal point or the focal
            length, ``principal_point`` and ``focal_length`` say whether the
            adjustment estimated it or why it stays held. None when it did not run.
        lens_distortion: the lens distortion the triplets' calibrated bundle adjustment
            found (:mod:`intrinsics.lens.distortion`): ``present``, ``params`` and
            ``std`` (COLMAP's order of the model's extra parameters), the
            likelihood-ratio ``statistic`` and its ``threshold``, and where the stored
            model cannot hold the lens the model that can (``richer_model``) with its
            fitted distortion (``richer_params``). None when the stored distortion was
            taken as it is.
        triplets: every triplet's tensor and how the constraints judged it.
        tensors: the tensors themselves (not written to JSON).
    """

    focal_search: dict[str, Any] | None = None
    diagnosis: str | None = None
    triplet_bundle: dict[str, Any] | None = None
    lens_distortion: dict[str, Any] | None = None
    triplets: list[TripletReport] = field(default_factory=list)
    tensors: list[TripletTensor] = field(default_factory=list, repr=False)


@dataclass(frozen=True)
class Provenance:
    """Where the calibration started and what it is for.

    Attributes:
        stored_camera: the camera as stored in the database (model, size, distortion)
            whose prior and model the calibration used: the group's first.
        group_cameras: the group's cameras as stored, for writing (each keeps its own
            distortion); ``[stored_camera]`` unless given.
        start_source: where the prior came from (one of :data:`START_SOURCES`); with
            ``EXIF focal length`` the focal search still checks it.
        reference: (fx, fy, cx, cy) the calibrated reconstruction itself holds (its
            bundle-adjusted intrinsics; the mean over the group's camera ids), pixels;
            None for a database.
    """

    stored_camera: CameraInfo | None = field(default=None, repr=False)
    group_cameras: list[CameraInfo] = field(default_factory=list, repr=False)
    start_source: str = "stored camera"
    reference: tuple[float, float, float, float] | None = None


#: The keys of :meth:`CameraCalibration.to_json`, in their order (DESIGN.md's contract:
#: scripts rely on them).
JSON_KEYS = (
    "camera_id",
    "model",
    "method",
    "fx",
    "fy",
    "cx",
    "cy",
    "std",
    "observable",
    "num_triplets",
    "num_inlier_triplets",
    "seconds",
    "prior",
    "start",
    "assumptions",
    "estimated",
    "unconstrained_std",
    "source",
    "focal_search",
    "diagnosis",
    "triplet_bundle",
    "lens_distortion",
    "distortion",
    "triplets",
    "stage_seconds",
    "tensor_starts",
    "reference",
    "camera_ids",
    "start_source",
)


def finite_or_none(value: float) -> float | None:
    """JSON-safe float: None for inf/NaN."""
    return float(value) if math.isfinite(value) else None
