"""Where a camera's calibration starts: the prior, its checks, COLMAP's guess.

Priors are (fx, fy, cx, cy) in pixels, COLMAP's pixel convention (the centre of the
top-left pixel at (0.5, 0.5)); a stored camera used as the start must be usable, and a
start must be one a camera of that size can have.
"""

from __future__ import annotations

import numpy as np

from ...common.errors import CalibrationError
from ...database.cameras import PINHOLE_MODELS, CameraInfo
from ..options import StartOptions

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


def start_source(camera: CameraInfo, options: StartOptions) -> str:
    """Where the starting intrinsics of ``camera`` come from (``START_SOURCES``)."""
    if options.prior is not None:
        return "--prior"
    if options.no_prior:
        return "default guess"
    return "EXIF focal length" if camera.has_prior_focal_length else "stored camera"
