"""Mapping (incremental or global) from a calibrated database and bundle adjustment.

The TrifocalCalib estimate is the camera's starting intrinsics. Mapping keeps
the parameters it determined fixed (a good calibration is what makes
registration reliable) and refines the others (``ba_refine_focal_length``,
``ba_refine_principal_point``); the optional final global bundle adjustment then
refines focal lengths and the principal point together with poses and points.
Distortion, which TrifocalCalib never estimates (it undistorts with the stored
parameters), is refined throughout when ``run`` asks for it: for camera models
that have it, as COLMAP does (``ba_refine_extra_params``).

Hard motion (:func:`incremental_mapping_with_retries`): when mapping finds no
initial pair or registers fewer than ``MIN_REGISTERED_FRACTION`` of the images,
it is retried with a smaller ``mapper.init_min_tri_angle`` (16° → 8° → 4°,
``INIT_TRI_ANGLES``). Driving sequences see little parallax between the frames
of a candidate pair, so that COLMAP's default finds no initial pair on a straight
drive even with the true K where a smaller angle does (docs/hard_scenes.md). COLMAP relaxes by
itself only when no model at all results (``init_min_num_inliers`` and
``init_min_tri_angle`` halved twice each, so 16° → 4°); a model of a few
images, which a driving sequence often gives, is not retried there.

Forward motion: COLMAP also rejects every initial pair whose unit baseline has
``|t_z| >= mapper.init_max_forward_motion`` (0.95) in the first camera, i.e. a
baseline within 18° of the optical axis, and no relaxation touches that limit. A
camera looking along a straight drive has ``|t_z|`` ≈ 1 for every pair, so no
angle gives a model there. The retries
after the first attempt are therefore *seeded*: the initial pair is the widest
pair (COLMAP's own two-view estimate with the calibrated K: median triangulation
angle) among the calibration's best triplets (:func:`choose_initial_pair`), given
to COLMAP as ``init_image_id1/2``, with the forward-motion limit lifted for that
pair only. Unseeded retries at 8° and 4° follow when the seeded ones fall short.
Each attempt starts at its angle; COLMAP's own relaxation inside an attempt
(``init_min_num_inliers`` and ``init_min_tri_angle`` halved, twice) may still
initialise below it (docs/hard_scenes.md).

Known focal length: COLMAP re-estimates the focal length while registering images
of a camera whose ``prior_focal_length`` flag is unset (the default of feature
extraction), and on forward motion, where the focal length barely shows in the
images, that estimate wanders far from a right start while the reprojection error
stays small. For the seeded
attempts ``run`` sets the flag of cameras whose focal length the calibration
estimated (:func:`focal_marked_known`); bundle adjustment still refines it when it
is not determined. The first attempt keeps COLMAP's behaviour: its per-image
estimate can pull a weakly determined focal length back towards the truth, which
the flag would prevent (docs/hard_scenes.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from ..common.bundle_adjustment import bundle_adjustment_options
from ..common.errors import CalibrationError
from ..common.log import keep_colmap_quiet, logger

REFINE_CHOICES = ("none", "ba")
MAPPERS = ("incremental", "global")
#: ``mapper.init_min_tri_angle`` tried in turn, degrees (COLMAP's default first).
INIT_TRI_ANGLES = (16.0, 8.0, 4.0)
#: A model registering fewer than this fraction of the images is retried.
MIN_REGISTERED_FRACTION = 0.5
#: COLMAP's ``mapper.init_max_forward_motion`` (|t_z| of the unit baseline).
DEFAULT_MAX_FORWARD_MOTION = 0.95
#: ``init_max_forward_motion`` of the seeded attempts: 1.0 lifts the limit.
SEEDED_MAX_FORWARD_MOTION = 1.0


@dataclass
class MappingAttempt:
    """One incremental mapping run: its initialisation settings and outcome."""

    init_min_tri_angle: float  # degrees
    num_registered_images: int  # in the largest model (0: no model)
    num_images: int
    #: ``init_image_id1/2`` given to COLMAP (None: COLMAP chose the pair).
    init_pair: tuple[int, int] | None = None
    #: ``mapper.init_max_forward_motion`` (|t_z| of the unit baseline; 1.0: no limit).
    init_max_forward_motion: float = DEFAULT_MAX_FORWARD_MOTION


@dataclass
class InitialPair:
    """A candidate initial pair as COLMAP's initialisation measures it (calibrated K).

    Attributes:
        image_ids: the two database image ids.
        tri_angle: median triangulation angle of the inlier matches, degrees.
        forward_motion: |t_z| of the unit baseline in the first camera (1: along
            the optical axis; COLMAP's default limit is 0.95).
        num_inliers: inlier matches of the calibrated two-view geometry.
    """

    image_ids: tuple[int, int]
    tri_angle: float
    forward_motion: float
    num_inliers: int


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
    init_pair: tuple[int, int] | None = None,
    init_max_forward_motion: float | None = None,
    refine_distortion: bool = False,
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
        init_pair: image ids of the initial pair (``init_image_id1/2``; None: COLMAP
            searches for one).
        init_max_forward_motion: ``mapper.init_max_forward_motion`` (None: COLMAP's 0.95).
        refine_distortion: refine the distortion parameters while mapping (COLMAP's
            default; TrifocalCalib never estimates them).
    """
    options = mapping_options(
        refine_intrinsics_while_mapping, seed, image_dir is not None, refine_distortion
    )
    if refine_principal_point is not None:
        options.ba_refine_principal_point = refine_principal_point
    if init_min_tri_angle is not None:
        options.mapper.init_min_tri_angle = init_min_tri_angle
    if init_pair is not None:
        options.init_image_id1, options.init_image_id2 = (int(i) for i in init_pair)
        # COLMAP re-tries a given pair init_num_trials (200) times per relaxation
        # step with the same seed, i.e. with the same outcome: once is enough.
        options.init_num_trials = 1
    if init_max_forward_motion is not None:
        options.mapper.init_max_forward_motion = init_max_forward_motion
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


def incremental_mapping_with_retries(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    refine_focal_length: bool = False,
    refine_principal_point: bool = False,
    seed: int = 0,
    progress: bool = False,
    angles: tuple[float, ...] = INIT_TRI_ANGLES,
    candidate_pairs: list[tuple[int, int]] | None = None,
    known_focal_cameras: list[int] | None = None,
    refine_distortion: bool = False,
) -> tuple[pycolmap.Reconstruction, list[MappingAttempt], InitialPair | None]:
    """Incremental mapping, retried with relaxed initialisation on hard motion.

    The first attempt is COLMAP's own search at ``angles[0]``. When its model
    registers fewer than ``MIN_REGISTERED_FRACTION`` of the images, the initial
    pair is chosen among ``candidate_pairs`` (:func:`choose_initial_pair`) and the
    other ``angles`` are tried seeded with it, the forward-motion limit lifted
    (``SEEDED_MAX_FORWARD_MOTION``); then unseeded at COLMAP's limit. The first
    model registering enough images ends the retries; otherwise the largest model
    of all attempts is returned.

    Args:
        database, image_dir, seed, progress: as :func:`incremental_mapping`.
        output_dir: receives one folder per attempt (``16``, ``8-seeded``, ``8``, ...).
        refine_focal_length, refine_principal_point: refined while mapping (the
            parameters the calibration did not determine).
        angles: ``mapper.init_min_tri_angle`` of the attempts, degrees.
        candidate_pairs: image-id pairs to seed the retries from (e.g. the pairs of
            the calibration's best triplets); None or empty: no seeded attempts.
        known_focal_cameras: cameras whose focal length the seeded attempts treat as
            known (:func:`focal_marked_known`; the database must be a copy this
            tool owns); the first and the unseeded attempts leave the flags alone.
        refine_distortion: refine the distortion parameters while mapping.

    Returns:
        The largest model, every attempt made, and the seeded pair (None when no
        retry was needed or no candidate qualified).

    Raises:
        CalibrationError: no attempt produced a model.
    """
    with pycolmap.Database.open(str(database)) as db:
        num_images = db.num_images()
    enough = MIN_REGISTERED_FRACTION * num_images
    attempts: list[MappingAttempt] = []
    best: pycolmap.Reconstruction | None = None
    chosen: InitialPair | None = None

    def attempt(angle: float, pair: tuple[int, int] | None, forward: float) -> int:
        nonlocal best
        folder = f"{angle:g}" + ("-seeded" if pair is not None else "")
        try:
            model = incremental_mapping(
                database,
                image_dir,
                output_dir / folder,
                refine_focal_length,
                seed,
                progress,
                init_min_tri_angle=angle,
                refine_principal_point=refine_principal_point,
                init_pair=pair,
                init_max_forward_motion=forward,
                refine_distortion=refine_distortion,
            )
        except CalibrationError:
            model = None
        registered = 0 if model is None else model.num_reg_images()
        attempts.append(MappingAttempt(angle, registered, num_images, pair, forward))
        logger.info(
            "mapping at init_min_tri_angle %g° (pair %s, max forward motion %g): %d registered",
            angle,
            pair,
            forward,
            registered,
        )
        if model is not None and (best is None or registered > best.num_reg_images()):
            best = model
        return registered

    done = attempt(angles[0], None, DEFAULT_MAX_FORWARD_MOTION) >= enough
    if not done and candidate_pairs and len(angles) > 1:
        chosen = choose_initial_pair(database, candidate_pairs, seed)
        if chosen is not None:
            logger.info(
                "seeded initial pair %d-%d: %.2f° triangulation angle, |t_z| %.4f, %d inliers",
                *chosen.image_ids,
                chosen.tri_angle,
                chosen.forward_motion,
                chosen.num_inliers,
            )
            with focal_marked_known(database, known_focal_cameras or []):
                for angle in angles[1:]:
                    if attempt(angle, chosen.image_ids, SEEDED_MAX_FORWARD_MOTION) >= enough:
                        done = True
                        break
    if not done:
        for angle in angles[1:]:
            if attempt(angle, None, DEFAULT_MAX_FORWARD_MOTION) >= enough:
                break
    if best is None:
        tried = ", ".join(dict.fromkeys(f"{a.init_min_tri_angle:g}°" for a in attempts))
        raise CalibrationError(
            f"incremental mapping registered no images (no initial pair at {tried})"
        )
    return best, attempts, chosen


def choose_initial_pair(
    database: Path,
    candidate_pairs: list[tuple[int, int]],
    seed: int = 0,
    min_num_inliers: int = 100,
    max_error: float = 4.0,
) -> InitialPair | None:
    """The candidate pair with the widest triangulation angle, as COLMAP's initialisation
    measures it; None when no candidate has ``min_num_inliers`` inliers.

    Each pair's verified matches get COLMAP's calibrated two-view estimate with the
    database's cameras (the calibrated K) and ``max_error`` px, as
    ``IncrementalMapper::EstimateInitialTwoViewGeometry`` does; the angle is the
    median triangulation angle of the inliers (degrees).
    """
    measured = measure_pairs(database, candidate_pairs, seed, max_error)
    usable = [p for p in measured if p.num_inliers >= min_num_inliers]
    if not usable:
        return None
    return max(usable, key=lambda p: p.tri_angle)


def measure_pairs(
    database: Path, pairs: list[tuple[int, int]], seed: int = 0, max_error: float = 4.0
) -> list[InitialPair]:
    """COLMAP's initial-pair measures (:class:`InitialPair`) of each pair with verified matches."""
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.min_num_trials = 30
    options.ransac.max_error = max_error
    options.ransac.random_seed = seed
    results = []
    with pycolmap.Database.open(str(database)) as db:
        for id1, id2 in dict.fromkeys(tuple(sorted(map(int, p))) for p in pairs):
            if id1 == id2 or not db.exists_two_view_geometry(id1, id2):
                continue
            matches = db.read_two_view_geometry(id1, id2).inlier_matches
            if len(matches) < 5:
                continue
            camera1 = db.read_camera(db.read_image(id1).camera_id)
            camera2 = db.read_camera(db.read_image(id2).camera_id)
            points1 = db.read_keypoints(id1)[:, :2].astype(np.float64)
            points2 = db.read_keypoints(id2)[:, :2].astype(np.float64)
            geometry = pycolmap.estimate_calibrated_two_view_geometry(
                camera1, points1, camera2, points2, matches, options
            )
            if not pycolmap.estimate_two_view_geometry_pose(
                camera1, points1, camera2, points2, geometry
            ):
                continue
            pose = geometry.cam2_from_cam1
            if pose is None:
                continue
            translation = np.asarray(pose.translation, dtype=float)
            norm = float(np.linalg.norm(translation))
            results.append(
                InitialPair(
                    (id1, id2),
                    float(np.rad2deg(geometry.tri_angle)),
                    abs(float(translation[2])) / norm if norm > 0 else 1.0,
                    len(geometry.inlier_matches),
                )
            )
    return results


def describe_attempts(
    attempts: list[MappingAttempt], seeded: InitialPair | None = None
) -> str | None:
    """One line saying what the retries did, or None when the first attempt sufficed."""
    if len(attempts) < 2:
        return None

    def label(a: MappingAttempt) -> str:
        if a.init_pair is None:
            return f"{a.init_min_tri_angle:g}°"
        return f"{a.init_min_tri_angle:g}° seeded {a.init_pair[0]}+{a.init_pair[1]}"

    steps = ", ".join(f"{label(a)}: {a.num_registered_images}/{a.num_images}" for a in attempts)
    line = f"mapping retried with relaxed initialisation (init_min_tri_angle {steps} registered"
    if seeded is not None:
        line += (
            f"; pair {seeded.image_ids[0]}+{seeded.image_ids[1]} from the calibration's best "
            f"triplets: {seeded.tri_angle:.1f}° triangulation angle, forward motion "
            f"{seeded.forward_motion:.3f}, limit {DEFAULT_MAX_FORWARD_MOTION:g} lifted"
        )
    return line + ")"


@contextmanager
def focal_marked_known(database: Path, camera_ids: list[int]) -> Iterator[None]:
    """Set COLMAP's ``prior_focal_length`` flag of ``camera_ids`` for the duration, then
    restore the stored flags (the database must be this tool's own copy).

    The mapper then keeps these focal lengths through image registration instead of
    re-estimating them per image (bundle adjustment still refines them when asked to).
    """
    with pycolmap.Database.open(str(database)) as db:
        saved = {}
        for camera_id in camera_ids:
            if db.exists_camera(camera_id):
                camera = db.read_camera(camera_id)
                saved[camera_id] = camera.has_prior_focal_length
                camera.has_prior_focal_length = True
                db.update_camera(camera)
    try:
        yield
    finally:
        with pycolmap.Database.open(str(database)) as db:
            for camera_id, flag in saved.items():
                camera = db.read_camera(camera_id)
                camera.has_prior_focal_length = flag
                db.update_camera(camera)


def mapping_options(
    refine_intrinsics: bool, seed: int, colours: bool, distortion: bool = False
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


def refine_intrinsics(reconstruction: pycolmap.Reconstruction, distortion: bool = False) -> None:
    """Global bundle adjustment of poses, points, focal lengths and principal points (and
    the distortion parameters with ``distortion``), in place."""
    options = bundle_adjustment_options(refine_extra_params=distortion)
    with keep_colmap_quiet():
        pycolmap.bundle_adjustment(reconstruction, options)


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
