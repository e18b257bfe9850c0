"""Mapping (incremental or global) from a calibrated database and bundle adjustment.

The TrifocalCalib estimate is the camera's starting intrinsics. Mapping keeps
them fixed (a good calibration is what makes registration reliable); the
optional final global bundle adjustment then refines focal lengths and the
principal point together with poses and points (distortion stays fixed).
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
    """
    options = mapping_options(refine_intrinsics_while_mapping, seed, image_dir is not None)
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
    if not models:
        raise CalibrationError("incremental mapping registered no images (no model)")
    largest = max(models.values(), key=lambda r: r.num_reg_images())
    logger.info(
        "mapping: %d model(s), largest with %d registered images",
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
    if not models:
        raise CalibrationError("global mapping registered no images (no model)")
    largest = max(models.values(), key=lambda r: r.num_reg_images())
    logger.info(
        "global mapping: %d model(s), largest with %d registered images",
        len(models),
        largest.num_reg_images(),
    )
    return largest


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


def refine_intrinsics(reconstruction: pycolmap.Reconstruction) -> None:
    """Global bundle adjustment refining focal lengths and principal points (in place)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = True
    options.refine_extra_params = False
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
