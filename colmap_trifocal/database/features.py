"""Feature extraction and matching into a COLMAP database (pycolmap SIFT).

With ``progress`` the work is cut into steps, each a pycolmap call, and a bar on stderr
moves after each one: the images are extracted a chunk at a time, and the image pairs
COLMAP's own pair generator gives (exhaustive or sequential) are matched a chunk at a
time from a pairs file (``pycolmap.match_image_pairs``). pycolmap gives no callback inside
one call, and reading the database while it writes would take SQLite locks of its own in
this process. Extraction of each image and matching of each pair do not depend on the
others, so the database holds the same cameras, features and matches either way.

The images and their cameras are imported first, in the order of their names, on one
thread (``pycolmap.import_images``, COLMAP's own reader with the extraction's camera
settings); the extraction then fills in their features. Extraction threads write the
images they create in the order they finish, so without the import an image's id (and
with it every pair id) changed from build to build; with it, and a seeded verification,
a build on any number of threads holds what a build on one thread holds. The import
decodes every image once more, on one thread, as COLMAP's reader does ahead of its
extraction threads (docs/reliability.md, "Determinism").

One part is pycolmap's and not exactly repeatable: its CPU matcher searches the
descriptors of an image with 512 features or more through a FAISS IVF index whose cells
k-means trains, and that build is not perfectly deterministic (colmap/colmap#3874), so
two builds can rarely differ in one image's matches.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Sequence
from pathlib import Path

import pycolmap
from tqdm import tqdm

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
        num_threads: threads of extraction and matching (-1: every core); the
            database does not depend on it (see the module).
        seed: the random seed of the geometric verification's RANSAC (None: random).
            With a seed the database is the same on every build, up to pycolmap's
            approximate descriptor search (the module's docstring).
        progress: bars of images extracted and pairs matched on stderr (the work done
            a chunk at a time, see the module docstring).
    """
    image_dir, database = Path(image_dir), Path(database)
    check_max_image_size(max_image_size)
    if database.exists():
        raise CalibrationError(f"database already exists: {database}")
    if matcher not in MATCHERS:
        raise CalibrationError(f"unknown matcher {matcher!r} (choose from {MATCHERS})")
    mode = _camera_mode(camera_mode, single_camera=single_camera)
    reader, extraction, matching, verification = _colmap_options(
        camera_model, max_image_size, num_threads, seed
    )
    _import(database, image_dir, image_names or [], mode, reader)
    if progress:
        names = image_names or sorted(p.name for p in image_dir.iterdir() if p.is_file())
        _extract_in_chunks(database, image_dir, names, mode, reader, extraction)
        _match_in_chunks(database, matcher, matching, verification)
    else:
        _extract(database, image_dir, image_names or [], mode, reader, extraction)
        match = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
        match(
            database,
            matching_options=matching,
            verification_options=verification,
            device=pycolmap.Device.cpu,
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
    camera_model: str, max_image_size: int, num_threads: int, seed: int | None
) -> tuple[
    pycolmap.ImageReaderOptions,
    pycolmap.FeatureExtractionOptions,
    pycolmap.FeatureMatchingOptions,
    pycolmap.TwoViewGeometryOptions,
]:
    """pycolmap's reader, extraction, matching and verification options of a build."""
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
    return reader, extraction, matching, verification


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


#: Steps of each progress bar (at least :data:`MIN_CHUNK` images or pairs per step).
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


def _match_in_chunks(
    database: Path,
    matcher: str,
    matching: pycolmap.FeatureMatchingOptions,
    verification: pycolmap.TwoViewGeometryOptions,
) -> None:
    """Match the pairs COLMAP's ``matcher`` pair generator gives, a chunk at a time from a
    pairs file next to the database (removed after), with a bar of image pairs."""
    with pycolmap.Database.open(str(database)) as db:
        if matcher == "exhaustive":
            generator = pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db)
            pairs = generator.all_pairs()
        else:
            sequential = pycolmap.SequentialPairGenerator(pycolmap.SequentialPairingOptions(), db)
            pairs = sequential.all_pairs()
        names = {image.image_id: image.name for image in db.read_all_images()}
        lines = [f"{names[a]} {names[b]}\n" for a, b in pairs]
    with (
        tempfile.TemporaryDirectory(dir=database.parent, prefix=".pairs-") as tmp,
        tqdm(total=len(lines), desc="matching: image pairs", unit="pair") as bar,
    ):
        pairs_file = Path(tmp) / "pairs.txt"
        for chunk in _chunks(lines):
            pairs_file.write_text("".join(chunk))
            options = pycolmap.ImportedPairingOptions()
            options.match_list_path = pairs_file
            pycolmap.match_image_pairs(
                database,
                matching_options=matching,
                pairing_options=options,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
            bar.update(len(chunk))
