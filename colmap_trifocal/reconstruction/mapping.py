"""Mapping (incremental or global) from a calibrated database and bundle adjustment.

The TrifocalCalib estimate is the camera's starting intrinsics: one run of a mapper is
:mod:`.mapping_runs`, the incremental mapper retried on hard motion
:mod:`.mapping_retries`; this module gives both and the bundle adjustment after them.
The optional final global bundle adjustment (:func:`refine_intrinsics`) refines focal
lengths and the principal point together with poses and points.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..common.bundle_adjustment import bundle_adjustment_options
from ..common.log import keep_colmap_quiet
from .mapping_retries import (
    DEFAULT_MAX_FORWARD_MOTION,
    INIT_TRI_ANGLES,
    MIN_REGISTERED_FRACTION,
    SEEDED_MAX_FORWARD_MOTION,
    InitialPair,
    MappingAttempt,
    RetryPlan,
    choose_initial_pair,
    describe_attempts,
    focal_marked_known,
    map_with_retries,
    measure_pairs,
)
from .mapping_runs import (
    Initialisation,
    Refinement,
    global_mapping,
    incremental_mapping,
    mapping_options,
)

__all__ = [
    "DEFAULT_MAX_FORWARD_MOTION",
    "INIT_TRI_ANGLES",
    "MAPPERS",
    "MIN_REGISTERED_FRACTION",
    "REFINE_CHOICES",
    "SEEDED_MAX_FORWARD_MOTION",
    "CameraRefinement",
    "Initialisation",
    "InitialPair",
    "MappingAttempt",
    "Refinement",
    "RetryPlan",
    "camera_intrinsics",
    "choose_initial_pair",
    "describe_attempts",
    "focal_marked_known",
    "global_mapping",
    "incremental_mapping",
    "map_with_retries",
    "mapping_options",
    "mean_reprojection_error",
    "measure_pairs",
    "refine_intrinsics",
    "registered_images_per_camera",
]

REFINE_CHOICES = ("none", "ba")
MAPPERS = ("incremental", "global")


@dataclass
class CameraRefinement:
    """Intrinsics before and after bundle adjustment for one camera (pixels)."""

    camera_id: int
    model: str
    before: np.ndarray  # (4,) fx, fy, cx, cy written before mapping
    after: np.ndarray  # (4,) after the final bundle adjustment (== before with refine none)
    num_registered_images: int


def camera_intrinsics(camera: pycolmap.Camera) -> np.ndarray:
    """(fx, fy, cx, cy) of a pycolmap camera (fx = fy for single-focal models)."""
    return np.array(
        [
            camera.focal_length_x,
            camera.focal_length_y,
            camera.principal_point_x,
            camera.principal_point_y,
        ]
    )


def refine_intrinsics(
    reconstruction: pycolmap.Reconstruction,
    *,
    distortion: bool = False,
    tied: Collection[int] = (),
) -> None:
    """Global bundle adjustment of poses, points, focal lengths and principal points (and
    the distortion parameters with ``distortion``), in place.

    The ``PINHOLE`` cameras whose ids are in ``tied`` keep ``fy = fx``: pycolmap refines
    a PINHOLE camera's fx and fy apart, so they are adjusted as ``SIMPLE_PINHOLE``, from
    the mean of the two, and written back as PINHOLE with the one focal length.
    """
    pinhole = pycolmap.CameraModelId.PINHOLE
    cameras = reconstruction.cameras
    single = [c for c in tied if c in cameras and cameras[c].model == pinhole]
    for camera_id in single:
        camera = reconstruction.cameras[camera_id]
        fx, fy, cx, cy = camera.params
        camera.model = pycolmap.CameraModelId.SIMPLE_PINHOLE
        camera.params = [(fx + fy) / 2, cx, cy]
    options = bundle_adjustment_options(refine_extra_params=distortion)
    try:
        with keep_colmap_quiet():
            pycolmap.bundle_adjustment(reconstruction, options)
    finally:
        for camera_id in single:
            camera = reconstruction.cameras[camera_id]
            f, cx, cy = camera.params
            camera.model = pinhole
            camera.params = [f, f, cx, cy]


def mean_reprojection_error(reconstruction: pycolmap.Reconstruction) -> float:
    """Mean reprojection error over all observations, pixels."""
    return float(reconstruction.compute_mean_reprojection_error())


def registered_images_per_camera(reconstruction: pycolmap.Reconstruction) -> dict[int, int]:
    """camera_id -> number of registered images."""
    counts: dict[int, int] = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            counts[image.camera_id] = counts.get(image.camera_id, 0) + 1
    return counts
