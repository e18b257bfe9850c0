"""What ``run`` gives: its report (``WORKSPACE/report.json``).

:class:`RunReport` is the run level of the results: per camera (a group of camera ids,
:class:`..intrinsics.results.CameraCalibration`) TrifocalCalib's estimate beside the
intrinsics the reconstruction ended with, then the reconstruction's size and error,
the mapping and the seconds of each stage. Intrinsics in pixels (COLMAP's pixel
convention, the centre of the top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pycolmap

from ..database.cameras import CameraInfo
from ..intrinsics.results import PARAMETER_NAMES, CameraCalibration, SkippedGroup
from .mapping import camera_intrinsics, mean_reprojection_error, registered_images_per_camera


@dataclass
class RunReport:
    """The report of one ``run``, as ``report.json`` holds it (:meth:`to_json`).

    Attributes:
        method, mapper, refine: the run's ``--method``, ``--mapper`` and ``--refine``.
        num_images: the images of the database the run mapped (registered or not).
        num_registered_images, num_points3D: the reconstruction's.
        mean_reprojection_error_px: over all observations, pixels.
        cameras: one object per camera registered in the reconstruction
            (:func:`camera_report`).
        seconds: wall seconds of each stage (features, calibrate, mapping, refine).
        mapping: the mapper, what it refined and its attempts (with a ``note`` when it
            retried); empty when the estimate went into a given model.
        skipped_cameras: the camera groups not calibrated (fewer than 3 images, or no
            estimate from them), mapped from their stored values with the focal length
            refined while mapping (:func:`skipped_camera_report`).
        skipped_images: the files with an image suffix the extraction did not get
            (``name``, ``reason``), as COLMAP skips what it cannot read.
    """

    method: str
    mapper: str
    refine: str
    num_images: int
    num_registered_images: int
    num_points3D: int
    mean_reprojection_error_px: float
    cameras: list[dict[str, Any]]
    seconds: dict[str, float]
    mapping: dict[str, Any] = field(default_factory=dict)
    skipped_cameras: list[dict[str, Any]] = field(default_factory=list)
    skipped_images: list[dict[str, str]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The ``report.json`` object (a copy: changing it leaves the report as it is)."""
        return asdict(self)


def build_report(  # noqa: PLR0913 (the report's parts: each a keyword, all from one run)
    reconstruction: pycolmap.Reconstruction,
    calibrations: list[CameraCalibration],
    *,
    num_images: int,
    method: str,
    mapper: str,
    refine: str,
    seconds: dict[str, float],
    mapping: dict[str, Any],
    skipped_cameras: list[tuple[SkippedGroup, list[CameraInfo]]] | None = None,
    skipped_images: list[dict[str, str]] | None = None,
) -> RunReport:
    """The report of a run that ended with ``reconstruction`` (see :class:`RunReport`).

    ``calibrations`` are the calibrate stage's results; a camera none of whose images
    was registered is left out. ``num_images``: the database's images (the mapper's
    model holds only those it registered). ``skipped_cameras``: each group the calibration skipped,
    with its cameras as stored.
    """
    registered = registered_images_per_camera(reconstruction)
    cameras = [
        camera_report(reconstruction, calibration, registered)
        for calibration in calibrations
        if any(c in reconstruction.cameras for c in calibration.camera_ids)
    ]
    skipped = [
        skipped_camera_report(reconstruction, group, stored, registered)
        for group, stored in skipped_cameras or []
    ]
    return RunReport(
        method=method,
        mapper=mapper,
        refine=refine,
        num_images=num_images,
        num_registered_images=reconstruction.num_reg_images(),
        num_points3D=reconstruction.num_points3D(),
        mean_reprojection_error_px=mean_reprojection_error(reconstruction),
        cameras=cameras,
        seconds=seconds,
        mapping=mapping,
        skipped_cameras=skipped,
        skipped_images=list(skipped_images or []),
    )


def camera_report(
    reconstruction: pycolmap.Reconstruction,
    calibration: CameraCalibration,
    registered: dict[int, int],
) -> dict[str, Any]:
    """One camera's object of the report: TrifocalCalib's estimate (``trifocal``, its
    std, distortion, what is determined and why) beside the reconstruction's
    (``refined``: the mean over the group's camera ids in it), their difference
    (refined − trifocal, pixels), its mean relative size, and the camera's model and
    distortion parameters after mapping (COLMAP's order; ``[]`` for pinhole models): the
    model is the stored one's, or the one that holds the lens where the tracks determine
    it (:meth:`.CameraCalibration.mapping_cameras`).

    Args:
        registered: camera id -> registered images (:func:`.registered_images_per_camera`).
    """
    ids = list(calibration.camera_ids)
    in_model = [c for c in ids if c in reconstruction.cameras]
    refined = np.mean([camera_intrinsics(reconstruction.cameras[c]) for c in in_model], axis=0)
    estimate = calibration.intrinsics
    distortion = [CameraInfo.from_pycolmap(reconstruction.cameras[c]).distortion for c in in_model]
    return {
        "camera_id": calibration.camera_id,
        "camera_ids": ids,
        "model": calibration.model,
        "trifocal": _named(estimate),
        "trifocal_std": calibration.std,
        "trifocal_distortion": calibration.lens_distortion,
        "observable": calibration.observable,
        "assumptions": calibration.assumptions,
        "source": calibration.source,
        "warning": calibration.warning(),
        "refined": _named(refined),
        "difference": _named(refined - estimate),
        "relative_difference": float(np.mean(np.abs(refined / estimate - 1))),
        "mapped_model": reconstruction.cameras[in_model[0]].model.name,
        "distortion": np.mean(distortion, axis=0).tolist(),
        "num_registered_images": sum(registered.get(c, 0) for c in ids),
    }


def skipped_camera_report(
    reconstruction: pycolmap.Reconstruction,
    group: SkippedGroup,
    stored: list[CameraInfo],
    registered: dict[int, int],
) -> dict[str, Any]:
    """One skipped group's object of the report: why it was skipped
    (:meth:`..intrinsics.results.SkippedGroup.to_json`), its stored intrinsics (the mean
    over its camera ids) and, where any of its images was registered, the intrinsics
    mapping gave it (``refined``, the mean over its camera ids in the model; else None)."""
    in_model = [c for c in group.camera_ids if c in reconstruction.cameras]
    refined = None
    if in_model and any(registered.get(c, 0) for c in in_model):
        values = [camera_intrinsics(reconstruction.cameras[c]) for c in in_model]
        refined = _named(np.mean(values, axis=0))
    return {
        **group.to_json(),
        "stored": _named(np.mean([camera.intrinsics for camera in stored], axis=0)),
        "refined": refined,
        "num_registered_images": sum(registered.get(c, 0) for c in group.camera_ids),
    }


def _named(intrinsics: np.ndarray) -> dict[str, float]:
    """``{"fx", "fy", "cx", "cy"}`` of (4,) intrinsics, pixels."""
    return dict(zip(PARAMETER_NAMES, map(float, intrinsics), strict=True))
