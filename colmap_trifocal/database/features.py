"""Feature extraction and matching into a COLMAP database (pycolmap SIFT).

The images and their cameras are imported first, in the order of their names, on one
thread (``pycolmap.import_images``, COLMAP's own reader with the extraction's camera
settings); the extraction then fills in their features. Extraction threads write the
images they create in the order they finish, so without the import an image's id (and
with it every pair id) changed from build to build. The import decodes every image once
more, on one thread, as COLMAP's reader does ahead of its extraction threads
(docs/reliability.md, "Determinism").

The pairs COLMAP's own pair generator gives (exhaustive or sequential) are then matched
and verified by :func:`.matching.match_pairs`: worker processes on one thread each, since
pycolmap's matcher on several threads of one process is not repeatable. With a seed, a
build on any number of cores holds what a build on one core holds.

With ``progress`` a bar on stderr follows each stage: the images are extracted a chunk at
a time (pycolmap gives no callback inside one call), and the matching bar follows the
pairs the workers have verified.

One part is pycolmap's and not exactly repeatable: its CPU matcher searches the
descriptors of an image with 512 features or more through a FAISS IVF index whose cells
k-means trains, and that build is not perfectly deterministic (colmap/colmap#3874), so
two builds can rarely differ in one image's matches.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import pycolmap
from tqdm import tqdm

from ..common.errors import CalibrationError
from .matching import match_pairs

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


def build_database(  # noqa: PLR0913 (COLMAP's extraction and matching settings, each a keyword)
    image_dir: Path,
    database: Path,
    image_names: list[str] | None = None,
    *,
    max_image_size: int = 1600,
    camera_model: str = "PINHOLE",
    matcher: str = "exhaustive",
    single_camera: bool = True,
    camera_mode: str | None = None,
    num_threads: int = -1,
    seed: int | None = None,
    progress: bool = False,
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
        num_threads: threads of extraction, and processes of matching (-1: every core
            this process may use); the database does not depend on it (see the module).
        seed: the random seed of the geometric verification's RANSAC (None: random).
            With a seed the database is the same on every build, up to pycolmap's
            approximate descriptor search (the module's docstring).
        progress: bars of images extracted and pairs matched on stderr (see the
            module docstring).
    """
    image_dir, database = Path(image_dir), Path(database)
    check_max_image_size(max_image_size)
    if database.exists():
        raise CalibrationError(f"database already exists: {database}")
    if matcher not in MATCHERS:
        raise CalibrationError(f"unknown matcher {matcher!r} (choose from {MATCHERS})")
    mode = _camera_mode(camera_mode, single_camera=single_camera)
    reader, extraction = _colmap_options(camera_model, max_image_size, num_threads)
    _import(database, image_dir, image_names or [], mode, reader)
    if progress:
        names = image_names or sorted(p.name for p in image_dir.iterdir() if p.is_file())
        _extract_in_chunks(database, image_dir, names, mode, reader, extraction)
    else:
        _extract(database, image_dir, image_names or [], mode, reader, extraction)
    match_pairs(
        database,
        _pairs(database, matcher),
        seed=seed,
        workers=_cores(num_threads),
        progress=progress,
    )
    return database


def _camera_mode(camera_mode: str | None, *, single_camera: bool) -> pycolmap.CameraMode:
    """pycolmap's camera mode: ``camera_mode``, or from ``single_camera`` when None."""
    if camera_mode is not None and camera_mode not in CAMERA_MODES:
        raise CalibrationError(f"unknown camera mode {camera_mode!r} (choose from {CAMERA_MODES})")
    if camera_mode is None:
        camera_mode = "single" if single_camera else "per-image"
    return CAMERA_MODES[camera_mode]


def _colmap_options(
    camera_model: str, max_image_size: int, num_threads: int
) -> tuple[pycolmap.ImageReaderOptions, pycolmap.FeatureExtractionOptions]:
    """pycolmap's reader and extraction options of a build."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_image_size
    extraction.num_threads = num_threads
    return reader, extraction


def _cores(num_threads: int) -> int:
    """``num_threads``, or with -1 (or any value below 1) the cores this process may use."""
    return num_threads if num_threads > 0 else len(os.sched_getaffinity(0))


def _pairs(database: Path, matcher: str) -> list[tuple[int, int]]:
    """The image pairs (image ids) of COLMAP's ``matcher`` pair generator, with its
    default options, in its order."""
    with pycolmap.Database.open(str(database)) as db:
        generator: pycolmap.PairGenerator = (
            pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
            if matcher == "exhaustive"
            else pycolmap.SequentialPairGenerator(pycolmap.SequentialPairingOptions(), db)
        )
        return [(int(a), int(b)) for a, b in generator.all_pairs()]


def _import(
    database: Path,
    image_dir: Path,
    names: list[str],
    mode: pycolmap.CameraMode,
    reader: pycolmap.ImageReaderOptions,
) -> None:
    """A new database at ``database`` holding the images ``names`` of ``image_dir`` (every
    image when empty) and their cameras, without features, with ids in name order."""
    with pycolmap.Database.open(str(database)):
        pass  # created with COLMAP's schema
    pycolmap.import_images(database, image_dir, camera_mode=mode, image_names=names, options=reader)


def _extract(
    database: Path,
    image_dir: Path,
    names: list[str],
    mode: pycolmap.CameraMode,
    reader: pycolmap.ImageReaderOptions,
    extraction: pycolmap.FeatureExtractionOptions,
) -> None:
    """One ``pycolmap.extract_features`` call over ``names`` (every image when empty)."""
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


#: Steps of the extraction's progress bar (at least :data:`MIN_CHUNK` images per step).
PROGRESS_STEPS = 20
MIN_CHUNK = 2


def _chunks(items: Sequence, steps: int = PROGRESS_STEPS) -> list[Sequence]:
    """``items`` cut into about ``steps`` consecutive chunks (at least MIN_CHUNK each)."""
    size = max(MIN_CHUNK, math.ceil(len(items) / steps))
    return [items[k : k + size] for k in range(0, len(items), size)]


def _extract_in_chunks(
    database: Path,
    image_dir: Path,
    names: list[str],
    mode: pycolmap.CameraMode,
    reader: pycolmap.ImageReaderOptions,
    extraction: pycolmap.FeatureExtractionOptions,
) -> None:
    """``pycolmap.extract_features`` a chunk of the imported images (:func:`_import`) at a
    time, with a bar of images. Each image keeps the camera the import gave it."""
    with tqdm(total=len(names), desc="features: images", unit="image") as bar:
        for chunk in _chunks(names):
            _extract(database, image_dir, list(chunk), mode, reader, extraction)
            bar.update(len(chunk))
