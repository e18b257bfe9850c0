"""The first stage of one camera's calibration: its prior, undistorted keypoints and matches.

Intrinsics are (fx, fy, cx, cy) in pixels, COLMAP's pixel convention (the centre of
the top-left pixel at (0.5, 0.5)). Keypoints of distorted camera models are
undistorted with each image's own stored camera (the distortion is kept fixed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...common.errors import NoEstimate
from ...common.log import logger
from ...database.cameras import CameraInfo, check_supported, undistort_to_pinhole
from ...database.snapshot import DatabaseContents
from ..options import StartOptions
from .prior import check_camera_values, check_prior, default_guess, start_source


@dataclass
class CameraInput:
    """One physical camera's data, shared by every method.

    Attributes:
        camera: the group's first stored camera (model, size, prior).
        prior: starting (fx, fy, cx, cy), pixels; fx = fy for single-focal models.
        keypoints: image id -> undistorted keypoints (m, 2), pixels.
        matches: (image id, image id) -> verified matches (k, 2) between the images.
    """

    camera: CameraInfo
    prior: np.ndarray
    keypoints: dict[int, np.ndarray]
    matches: dict[tuple[int, int], np.ndarray]


def camera_input(
    contents: DatabaseContents,
    camera: CameraInfo,
    image_ids: list[int],
    options: StartOptions,
) -> CameraInput:
    """The prior (``--prior``, ``--no-prior`` or the stored camera), checked, and the
    images' undistorted keypoints and verified matches.

    Raises:
        CalibrationError: an unsupported model, or unusable stored values or prior.
        NoEstimate: fewer than 3 images, or no verified match between them.
    """
    check_supported(camera)
    if len(image_ids) < 3:
        raise NoEstimate(
            f"camera {camera.camera_id} has {len(image_ids)} image(s); at least 3 are needed"
        )
    if start_source(camera, options) == "EXIF focal length":
        logger.info(
            "camera %d: starting from the EXIF focal length %.1f px%s",
            camera.camera_id,
            camera.intrinsics[0],
            " (checked by the focal search)" if options.focal_search else "",
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
        raise NoEstimate(f"camera {camera.camera_id}: no verified matches between its images")
    return CameraInput(camera, prior, keypoints, matches)
