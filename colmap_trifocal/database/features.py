"""Feature extraction and matching into a COLMAP database (pycolmap SIFT)."""

from __future__ import annotations

from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError

MATCHERS = ("exhaustive", "sequential")
#: Longest image side for SIFT, in pixels: from a size that still has features up to the
#: largest value COLMAP's option (a C++ ``int``) holds (no downscaling in practice).
MAX_IMAGE_SIZE_RANGE = (100, 2**31 - 1)
#: pycolmap's camera modes: ``auto`` is COLMAP's default (``colmap feature_extractor``,
#: the GUI, ``pycolmap.extract_features``): measured with pycolmap 4.2.1, one camera
#: per image, all with the same parameters when the images share size and EXIF data.
CAMERA_MODES = {
    "auto": pycolmap.CameraMode.AUTO,
    "single": pycolmap.CameraMode.SINGLE,
    "per-folder": pycolmap.CameraMode.PER_FOLDER,
    "per-image": pycolmap.CameraMode.PER_IMAGE,
}


def check_max_image_size(value: int) -> None:
    """Raise CalibrationError unless ``value`` is an integer in :data:`MAX_IMAGE_SIZE_RANGE`."""
    low, high = MAX_IMAGE_SIZE_RANGE
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise CalibrationError(
            f"max image size must be an integer in [{low}, {high}] pixels, got {value!r}"
        )


def build_database(
    image_dir: Path,
    database: Path,
    image_names: list[str] | None = None,
    max_image_size: int = 1600,
    camera_model: str = "PINHOLE",
    matcher: str = "exhaustive",
    single_camera: bool = True,
    camera_mode: str | None = None,
    num_threads: int = -1,
    seed: int | None = None,
) -> Path:
    """Extract SIFT features (CPU) and match them, writing a new COLMAP database.

    Args:
        image_dir: folder of images.
        database: output database path (must not exist).
        image_names: images to use (default: all images pycolmap can read).
        max_image_size: images are downscaled to this longest side for SIFT;
            keypoints are stored in full-resolution pixel coordinates.
        camera_model: COLMAP model of the camera created by pycolmap (with its
            default initial guess, f = 1.2 · max(width, height), centred principal point).
        matcher: ``exhaustive`` or ``sequential``.
        single_camera: one camera for all images (True) or one per image.
        camera_mode: one of ``CAMERA_MODES`` (overrides ``single_camera``); ``auto`` is
            what COLMAP's own tools do.
        num_threads: threads of extraction and matching (-1: every core). With one
            thread and a ``seed`` the database is the same on every build; with more,
            pycolmap's threads give images their ids in the order they finish.
        seed: the random seed of the geometric verification's RANSAC (None: random).
    """
    image_dir, database = Path(image_dir), Path(database)
    check_max_image_size(max_image_size)
    if database.exists():
        raise CalibrationError(f"database already exists: {database}")
    if matcher not in MATCHERS:
        raise CalibrationError(f"unknown matcher {matcher!r} (choose from {MATCHERS})")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = num_threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    if seed is not None:
        verification.ransac.random_seed = seed
    if camera_mode is not None and camera_mode not in CAMERA_MODES:
        raise CalibrationError(f"unknown camera mode {camera_mode!r} (choose from {CAMERA_MODES})")
    if camera_mode is None:
        camera_mode = "single" if single_camera else "per-image"
    mode = CAMERA_MODES[camera_mode]
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=image_names or [],
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    match = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
    match(
        database,
        matching_options=matching,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    return database
