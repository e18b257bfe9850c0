"""Writing estimated cameras into a reconstruction in memory: every camera checked
before any is written (:meth:`.results.CameraCalibration.apply` writes databases through
:mod:`..database.camera_targets`).
"""

from __future__ import annotations

from collections.abc import Mapping

import pycolmap

from ..common.errors import CalibrationError
from ..database.camera_targets import check_same_camera
from ..database.cameras import CameraInfo


def apply_cameras(
    reconstruction: pycolmap.Reconstruction,
    cameras: Mapping[int, CameraInfo],
    *,
    require_all: bool = True,
) -> list[int]:
    """Write each camera's params into the reconstruction's camera of the same id.

    Every camera is checked before any is written, so a refusal leaves the
    reconstruction unchanged.

    Args:
        reconstruction: changed in memory.
        cameras: camera_id -> camera with the params to write (model and size must be
            those of the reconstruction's camera).
        require_all: refuse a camera id the reconstruction lacks (else it is skipped,
            but at least one must be there).

    Returns:
        The camera ids written (sorted).

    Raises:
        CalibrationError: a missing camera id (with ``require_all``), none present, or a
            camera of another model or image size.
    """
    present = sorted(c for c in cameras if reconstruction.exists_camera(c))
    missing = sorted(set(cameras) - set(present))
    if missing and require_all:
        raise CalibrationError(
            f"the reconstruction has no camera {missing[0]} (it has camera ids "
            f"{sorted(reconstruction.cameras)[:10]}): is it from this database?"
        )
    if not present:
        raise CalibrationError(
            "no camera of the reconstruction has a calibrated camera's id "
            "(is it from this database?)"
        )
    for camera_id in present:
        check_same_camera(
            camera_id, reconstruction.camera(camera_id), cameras[camera_id], "the reconstruction"
        )
    for camera_id in present:
        reconstruction.camera(camera_id).params = cameras[camera_id].params.tolist()
    return present
