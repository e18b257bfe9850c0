"""Feature extraction and matching into a COLMAP database (pycolmap SIFT)."""

from __future__ import annotations

from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError

MATCHERS = ("exhaustive", "sequential")


def build_database(
    image_dir: Path,
    database: Path,
    image_names: list[str] | None = None,
    max_image_size: int = 1600,
    camera_model: str = "PINHOLE",
    matcher: str = "exhaustive",
    single_camera: bool = True,
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
    """
    image_dir, database = Path(image_dir), Path(database)
    if database.exists():
        raise CalibrationError(f"database already exists: {database}")
    if matcher not in MATCHERS:
        raise CalibrationError(f"unknown matcher {matcher!r} (choose from {MATCHERS})")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=image_names or [],
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(database, device=pycolmap.Device.cpu)
    return database
