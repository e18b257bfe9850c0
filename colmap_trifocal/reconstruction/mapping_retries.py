"""Incremental mapping retried with relaxed initialisation on hard motion.

When mapping finds no initial pair or registers fewer than ``MIN_REGISTERED_FRACTION``
of the images, it is retried with a smaller ``mapper.init_min_tri_angle`` (16° → 8° →
4°, ``INIT_TRI_ANGLES``). Driving sequences see little parallax between the frames of a
candidate pair, so that COLMAP's default finds no initial pair on a straight drive even
with the true K where a smaller angle does (docs/hard_scenes.md). COLMAP relaxes by
itself only when no model at all results (``init_min_num_inliers`` and
``init_min_tri_angle`` halved twice each, so 16° → 4°); a model of a few images, which a
driving sequence often gives, is not retried there.

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

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.log import logger
from .mapping_runs import Initialisation, Refinement, incremental_mapping

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


@dataclass(frozen=True)
class RetryPlan:
    """Which attempts :func:`map_with_retries` may make.

    Attributes:
        angles: ``mapper.init_min_tri_angle`` of the attempts, degrees.
        candidate_pairs: image-id pairs to seed the retries from (e.g. the pairs of
            the calibration's best triplets); None or empty: no seeded attempts.
        known_focal_cameras: cameras whose focal length the seeded attempts treat as
            known (:func:`focal_marked_known`; the database must be a copy this
            tool owns); the first and the unseeded attempts leave the flags alone.
    """

    angles: tuple[float, ...] = INIT_TRI_ANGLES
    candidate_pairs: Sequence[tuple[int, int]] | None = None
    known_focal_cameras: Sequence[int] | None = None


@dataclass
class _Attempts:
    """The attempts of one :func:`map_with_retries`, and the largest model so far."""

    database: Path
    image_dir: Path | None
    output_dir: Path
    refine: Refinement
    seed: int
    progress: bool
    num_images: int
    made: list[MappingAttempt] = field(default_factory=list)
    best: pycolmap.Reconstruction | None = None

    def run(self, angle: float, pair: tuple[int, int] | None, forward: float) -> int:
        """One attempt (into ``output_dir/<angle>[-seeded]``); its registered images."""
        folder = f"{angle:g}" + ("-seeded" if pair is not None else "")
        try:
            model = incremental_mapping(
                self.database,
                self.image_dir,
                self.output_dir / folder,
                refine=self.refine,
                init=Initialisation(angle, pair, forward),
                seed=self.seed,
                progress=self.progress,
            )
        except CalibrationError:
            model = None
        registered = 0 if model is None else model.num_reg_images()
        self.made.append(MappingAttempt(angle, registered, self.num_images, pair, forward))
        logger.info(
            "mapping at init_min_tri_angle %g° (pair %s, max forward motion %g): %d registered",
            angle,
            pair,
            forward,
            registered,
        )
        if model is not None and (self.best is None or registered > self.best.num_reg_images()):
            self.best = model
        return registered


def map_with_retries(
    database: Path,
    image_dir: Path | None,
    output_dir: Path,
    *,
    refine: Refinement | None = None,
    plan: RetryPlan | None = None,
    seed: int = 0,
    progress: bool = False,
) -> tuple[pycolmap.Reconstruction, list[MappingAttempt], InitialPair | None]:
    """Incremental mapping, retried with relaxed initialisation on hard motion.

    The first attempt is COLMAP's own search at ``plan.angles[0]``. When its model
    registers fewer than ``MIN_REGISTERED_FRACTION`` of the images, the initial
    pair is chosen among ``plan.candidate_pairs`` (:func:`choose_initial_pair`) and the
    other angles are tried seeded with it, the forward-motion limit lifted
    (``SEEDED_MAX_FORWARD_MOTION``); then unseeded at COLMAP's limit. The first
    model registering enough images ends the retries; otherwise the largest model
    of all attempts is returned.

    Args:
        database, image_dir, seed, progress: as :func:`.mapping_runs.incremental_mapping`.
        output_dir: receives one folder per attempt (``16``, ``8-seeded``, ``8``, ...).
        refine: refined while mapping (the parameters the calibration did not
            determine; None: nothing).
        plan: the attempts allowed (None: :class:`RetryPlan`'s defaults).

    Returns:
        The largest model, every attempt made, and the seeded pair (None when no
        retry was needed or no candidate qualified).

    Raises:
        CalibrationError: no attempt produced a model.
    """
    plan = plan or RetryPlan()
    with pycolmap.Database.open(str(database)) as db:
        num_images = db.num_images()
    enough = MIN_REGISTERED_FRACTION * num_images
    attempts = _Attempts(
        database, image_dir, output_dir, refine or Refinement(), seed, progress, num_images
    )
    chosen: InitialPair | None = None
    done = attempts.run(plan.angles[0], None, DEFAULT_MAX_FORWARD_MOTION) >= enough
    if not done and plan.candidate_pairs and len(plan.angles) > 1:
        chosen, done = _seeded_attempts(attempts, plan, enough)
    if not done:
        for angle in plan.angles[1:]:
            if attempts.run(angle, None, DEFAULT_MAX_FORWARD_MOTION) >= enough:
                break
    if attempts.best is None:
        tried = ", ".join(dict.fromkeys(f"{a.init_min_tri_angle:g}°" for a in attempts.made))
        raise CalibrationError(
            f"incremental mapping registered no images (no initial pair at {tried})"
        )
    return attempts.best, attempts.made, chosen


def _seeded_attempts(
    attempts: _Attempts, plan: RetryPlan, enough: float
) -> tuple[InitialPair | None, bool]:
    """The seeded retries at ``plan.angles[1:]``: the pair chosen (None: no candidate
    qualified) and whether one registered ``enough`` images."""
    chosen = choose_initial_pair(attempts.database, list(plan.candidate_pairs or []), attempts.seed)
    if chosen is None:
        return None, False
    logger.info(
        "seeded initial pair %d-%d: %.2f° triangulation angle, |t_z| %.4f, %d inliers",
        *chosen.image_ids,
        chosen.tri_angle,
        chosen.forward_motion,
        chosen.num_inliers,
    )
    with focal_marked_known(attempts.database, list(plan.known_focal_cameras or [])):
        for angle in plan.angles[1:]:
            if attempts.run(angle, chosen.image_ids, SEEDED_MAX_FORWARD_MOTION) >= enough:
                return chosen, True
    return chosen, False


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
