"""Mapping (incremental or global) from a calibrated database and bundle adjustment.

The TrifocalCalib estimate is the camera's starting intrinsics. Mapping keeps
the parameters it determined fixed (a good calibration is what makes
registration reliable) and refines the others (``ba_refine_focal_length``,
``ba_refine_principal_point``); the optional final global bundle adjustment then
refines focal lengths and the principal point together with poses and points
(distortion stays fixed).

Hard motion (:func:`incremental_mapping_with_retries`): when mapping finds no
initial pair or registers fewer than ``MIN_REGISTERED_FRACTION`` of the images,
it is retried with a smaller ``mapper.init_min_tri_angle`` (16° → 8° → 4°,
``INIT_TRI_ANGLES``). Driving sequences see little parallax between the frames
of a candidate pair: on a straight 51-frame KITTI drive COLMAP's 16° found no
initial pair even with the true K, 4° registered all frames. COLMAP relaxes by
itself only when no model at all results (``init_min_num_inliers`` and
``init_min_tri_angle`` halved twice each, so 16° → 4°); a model of a few
images, which a driving sequence often gives, is not retried there.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from ..common.errors import CalibrationError
from ..common.log import logger

REFINE_CHOICES = ("none", "ba")
MAPPERS = ("incremental", "global")
#: ``mapper.init_min_tri_angle`` tried in turn, degrees (COLMAP's default first).
INIT_TRI_ANGLES = (16.0, 8.0, 4.0)
#: A model registering fewer than this fraction of the images is retried.
MIN_REGISTERED_FRACTION = 0.5


@dataclass
class MappingAttempt:
    """One incremental mapping run: its initial triangulation angle and outcome."""

    init_min_tri_angle: float  # degrees
    num_registered_images: int  # in the largest model (0: no model)
    num_images: int


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


def incremental_mapping(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    refine_intrinsics_while_mapping: bool = False,
    seed: int = 0,
    progress: bool = False,
    init_min_tri_angle: float | None = None,
    refine_principal_point: bool | None = None,
) -> pycolmap.Reconstruction:
    """pycolmap incremental mapping; returns the largest model, written to ``output_dir/0``.

    Args:
        database: COLMAP database with verified matches and the starting cameras.
        image_dir: the images (only used for point colours; None: no colours).
        output_dir: folder receiving the models (``0``, ``1``, ...; the largest first).
        refine_intrinsics_while_mapping: let mapping's bundle adjustments refine
            focal length and principal point (COLMAP's default refines focal only);
            False keeps the cameras fixed at their starting values.
        seed: random seed of the mapper.
        progress: show a bar of registered images.
        init_min_tri_angle: ``mapper.init_min_tri_angle`` in degrees (None: COLMAP's 16°).
        refine_principal_point: refine the principal point while mapping (None: as
            ``refine_intrinsics_while_mapping``).
    """
    options = mapping_options(refine_intrinsics_while_mapping, seed, image_dir is not None)
    if refine_principal_point is not None:
        options.ba_refine_principal_point = refine_principal_point
    if init_min_tri_angle is not None:
        options.mapper.init_min_tri_angle = init_min_tri_angle
    output_dir.mkdir(parents=True, exist_ok=True)
    with pycolmap.Database.open(str(database)) as db:
        num_images = db.num_images()
    bar = tqdm(total=num_images, desc="mapping: registered images", disable=not progress)
    # pycolmap insists on an existing image folder even when colours are not extracted.
    try:
        models = pycolmap.incremental_mapping(
            database,
            image_dir if image_dir is not None else output_dir,
            output_dir,
            options,
            initial_image_pair_callback=lambda: bar.update(2),
            next_image_callback=lambda: bar.update(1),
        )
    finally:
        bar.close()
    return _largest_model(models, "incremental mapping")


def _largest_model(
    models: dict[int, pycolmap.Reconstruction], mapper: str
) -> pycolmap.Reconstruction:
    """The model with most registered images; CalibrationError when there is none."""
    if not models:
        raise CalibrationError(f"{mapper} registered no images (no model)")
    largest = max(models.values(), key=lambda r: r.num_reg_images())
    logger.info(
        "%s: %d model(s), largest with %d registered images",
        mapper,
        len(models),
        largest.num_reg_images(),
    )
    return largest


def global_mapping(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    refine_intrinsics_while_mapping: bool | None = False,
    seed: int = 0,
) -> pycolmap.Reconstruction:
    """pycolmap's global mapper (GLOMAP); returns the largest model, written to ``output_dir``.

    Args:
        database: COLMAP database with verified matches and the starting cameras.
        image_dir: the images (point colours; None: no colours).
        output_dir: folder receiving the models.
        refine_intrinsics_while_mapping: False holds the cameras at their starting
            values through the mapper's bundle adjustments (the TrifocalCalib start);
            None keeps pycolmap's defaults (focal length and distortion refined, the
            principal point never), i.e. plain COLMAP.
        seed: random seed of the mapper.
    """
    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = seed
    options.mapper.random_seed = seed
    options.mapper.global_positioning.use_gpu = False
    options.mapper.bundle_adjustment.ceres.use_gpu = False
    if refine_intrinsics_while_mapping is not None:
        ba = options.mapper.bundle_adjustment
        ba.refine_focal_length = refine_intrinsics_while_mapping
        ba.refine_principal_point = refine_intrinsics_while_mapping
        ba.refine_extra_params = False
    output_dir.mkdir(parents=True, exist_ok=True)
    with keep_colmap_quiet():
        models = pycolmap.global_mapping(
            database, image_dir if image_dir is not None else output_dir, output_dir, options
        )
    return _largest_model(models, "global mapping")


def incremental_mapping_with_retries(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    refine_focal_length: bool = False,
    refine_principal_point: bool = False,
    seed: int = 0,
    progress: bool = False,
    angles: tuple[float, ...] = INIT_TRI_ANGLES,
) -> tuple[pycolmap.Reconstruction, list[MappingAttempt]]:
    """Incremental mapping, retried with relaxed initialisation on hard motion.

    Tries ``angles`` (``mapper.init_min_tri_angle``, degrees) in turn and stops at
    the first model registering at least ``MIN_REGISTERED_FRACTION`` of the
    images; otherwise the largest model of all attempts is returned.

    Args:
        database, image_dir, seed, progress: as :func:`incremental_mapping`.
        output_dir: receives one folder per attempt (``16``, ``8``, ``4``).
        refine_focal_length, refine_principal_point: refined while mapping (the
            parameters the calibration did not determine).

    Returns:
        The largest model and every attempt made.

    Raises:
        CalibrationError: no attempt produced a model.
    """
    with pycolmap.Database.open(str(database)) as db:
        num_images = db.num_images()
    attempts: list[MappingAttempt] = []
    best: pycolmap.Reconstruction | None = None
    for angle in angles:
        try:
            model = incremental_mapping(
                database,
                image_dir,
                output_dir / f"{angle:g}",
                refine_focal_length,
                seed,
                progress,
                init_min_tri_angle=angle,
                refine_principal_point=refine_principal_point,
            )
        except CalibrationError:
            model = None
        registered = 0 if model is None else model.num_reg_images()
        attempts.append(MappingAttempt(angle, registered, num_images))
        logger.info("mapping at init_min_tri_angle %g°: %d images registered", angle, registered)
        if model is not None and (best is None or registered > best.num_reg_images()):
            best = model
        if registered >= MIN_REGISTERED_FRACTION * num_images:
            break
    if best is None:
        tried = ", ".join(f"{a:g}°" for a in angles[: len(attempts)])
        raise CalibrationError(
            f"incremental mapping registered no images (no initial pair at {tried})"
        )
    return best, attempts


def describe_attempts(attempts: list[MappingAttempt]) -> str | None:
    """One line saying what the retries did, or None when the first attempt sufficed."""
    if len(attempts) < 2:
        return None
    steps = ", ".join(
        f"{a.init_min_tri_angle:g}°: {a.num_registered_images}/{a.num_images}" for a in attempts
    )
    return f"mapping retried with relaxed initialisation (init_min_tri_angle {steps} registered)"


def mapping_options(
    refine_intrinsics: bool, seed: int, colours: bool
) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping options: focal length and principal point refined while
    mapping (or both held), distortion held, seeded; point colours read from the images."""
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.ba_refine_focal_length = refine_intrinsics
    options.ba_refine_principal_point = refine_intrinsics
    options.ba_refine_extra_params = False
    options.extract_colors = colours
    return options


def refine_intrinsics(reconstruction: pycolmap.Reconstruction, distortion: bool = False) -> None:
    """Global bundle adjustment of poses, points, focal lengths and principal points (and
    the distortion parameters with ``distortion``), in place."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = True
    options.refine_extra_params = distortion
    options.print_summary = False
    with keep_colmap_quiet():
        pycolmap.bundle_adjustment(reconstruction, options)


@contextmanager
def keep_colmap_quiet() -> Iterator[None]:
    """Keep COLMAP's log level across a call that resets it.

    Measured with pycolmap 4.2: ``pycolmap.bundle_adjustment`` sets glog's
    ``minloglevel`` to 0 and prints two INFO lines even when the level was 2. When
    COLMAP is quiet, stderr (file descriptor 2, where glog writes) is silenced for
    the call and the level restored afterwards.
    """
    level = pycolmap.logging.minloglevel
    if level < 1:
        yield
        return
    try:
        with silenced_stderr():
            yield
    finally:
        pycolmap.logging.minloglevel = level


@contextmanager
def silenced_stderr() -> Iterator[None]:
    """Send file descriptor 2 (where glog, COLMAP's logger, writes) to /dev/null."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


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
