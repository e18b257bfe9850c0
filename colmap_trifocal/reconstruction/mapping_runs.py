"""One run of pycolmap's incremental or global mapper from a calibrated database.

The TrifocalCalib estimate is the camera's starting intrinsics. Mapping keeps the
parameters it determined fixed (a good calibration is what makes registration reliable)
and refines the others (:class:`Refinement`: ``ba_refine_focal_length``,
``ba_refine_principal_point``). Distortion, which TrifocalCalib never estimates (it
undistorts with the stored parameters), is refined throughout when ``run`` asks for it:
for camera models that have it, as COLMAP does (``ba_refine_extra_params``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pycolmap
from tqdm import tqdm

from ..common.errors import CalibrationError
from ..common.log import keep_colmap_quiet, logger


@dataclass(frozen=True)
class Refinement:
    """What the mapper's bundle adjustments refine (False: held at the starting values).

    Attributes:
        focal_length: the focal lengths.
        principal_point: the principal points.
        distortion: the distortion parameters (COLMAP's default; TrifocalCalib never
            estimates them).
    """

    focal_length: bool = False
    principal_point: bool = False
    distortion: bool = False


@dataclass(frozen=True)
class Initialisation:
    """How the incremental mapper chooses its initial pair (None: COLMAP's default).

    Attributes:
        min_tri_angle: ``mapper.init_min_tri_angle`` in degrees (COLMAP's 16°).
        pair: image ids of the initial pair (``init_image_id1/2``; COLMAP searches for one).
        max_forward_motion: ``mapper.init_max_forward_motion`` (COLMAP's 0.95).
    """

    min_tri_angle: float | None = None
    pair: tuple[int, int] | None = None
    max_forward_motion: float | None = None


def incremental_mapping(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    *,
    refine: Refinement | None = None,
    init: Initialisation | None = None,
    seed: int = 0,
    progress: bool = False,
) -> pycolmap.Reconstruction:
    """pycolmap incremental mapping; returns the largest model, written to ``output_dir/0``.

    Args:
        database: COLMAP database with verified matches and the starting cameras.
        image_dir: the images (only used for point colours; None: no colours).
        output_dir: folder receiving the models (``0``, ``1``, ...; the largest first).
        refine: what mapping's bundle adjustments refine (None: nothing, the cameras
            held at their starting values).
        init: the initial pair's settings (None: COLMAP's).
        seed: random seed of the mapper.
        progress: show a bar of registered images.
    """
    refine = refine or Refinement()
    options = mapping_options(
        refine_intrinsics=refine.focal_length,
        seed=seed,
        colours=image_dir is not None,
        distortion=refine.distortion,
    )
    options.ba_refine_principal_point = refine.principal_point
    _set_initialisation(options, init or Initialisation())
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


def _set_initialisation(options: pycolmap.IncrementalPipelineOptions, init: Initialisation) -> None:
    """Write ``init``'s settings that are not None into ``options``."""
    if init.min_tri_angle is not None:
        options.mapper.init_min_tri_angle = init.min_tri_angle
    if init.pair is not None:
        options.init_image_id1, options.init_image_id2 = (int(i) for i in init.pair)
        # COLMAP re-tries a given pair init_num_trials (200) times per relaxation
        # step with the same seed, i.e. with the same outcome: once is enough.
        options.init_num_trials = 1
    if init.max_forward_motion is not None:
        options.mapper.init_max_forward_motion = init.max_forward_motion


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
    *,
    refine_intrinsics_while_mapping: bool | None = False,
    seed: int = 0,
    refine_distortion: bool = False,
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
        refine_distortion: with ``refine_intrinsics_while_mapping`` not None, refine
            the distortion parameters too.
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
        ba.refine_extra_params = refine_distortion
    output_dir.mkdir(parents=True, exist_ok=True)
    with keep_colmap_quiet():
        models = pycolmap.global_mapping(
            database, image_dir if image_dir is not None else output_dir, output_dir, options
        )
    return _largest_model(models, "global mapping")


def mapping_options(
    *, refine_intrinsics: bool, seed: int, colours: bool, distortion: bool = False
) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping options: focal length and principal point refined while
    mapping (or both held), distortion refined with ``distortion`` (else held), seeded;
    point colours read from the images."""
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.ba_refine_focal_length = refine_intrinsics
    options.ba_refine_principal_point = refine_intrinsics
    options.ba_refine_extra_params = distortion
    options.extract_colors = colours
    return options
