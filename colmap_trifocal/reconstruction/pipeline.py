"""From a COLMAP database to a calibrated ``pycolmap.Reconstruction`` in one call.

:func:`reconstruct` is the stages of ``colmap-trifocal run`` after feature matching, on a
database the caller already has:

1. calibrate: the camera ids grouped into physical cameras and TrifocalCalib per group
   (``intrinsics``), in a working copy of the database (``database.db`` of a temporary
   folder; the user's database is read, never changed, unless ``write``);
2. prepare: the estimate written into the copy as each camera's starting intrinsics, and
   the images of each group moved onto the group's first camera, so that mapping and
   bundle adjustment refine one camera per group, as the images share one lens;
3. map: pycolmap incremental or global mapping from the copy, the intrinsics the tracks
   gave the calibration held fixed, a focal length it held at its start (and the
   distortion of models that have it) refined (:func:`refined_while_mapping`);
   incremental mapping retried with relaxed initialisation on hard
   motion (:func:`.mapping_retries.map_with_retries`);
4. refine (``refine="ba"``): the global bundle adjustment of ``run`` (focal lengths and
   principal points with poses and points); ``"none"`` (the default) keeps the estimate.

The same stages run ``run`` (:mod:`.workflow`), which adds the features, the workspace
and the report. Intrinsics are in pixels, COLMAP's pixel convention (the centre of the
top-left pixel at (0.5, 0.5)).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pycolmap

from ..common.errors import CalibrationError
from ..common.log import logger
from ..database.cameras import PINHOLE_MODELS, CameraInfo
from ..database.shared_cameras import merge_group_cameras
from ..database.snapshot import DatabaseContents, read_database
from ..database.sqlite_files import copy_database
from ..database.writing import write_intrinsics
from ..intrinsics.api import (
    CalibrationOptions,
    calibrate_groups,
    check_options,
    tied_focal_cameras,
    updated_cameras,
)
from ..intrinsics.results import CameraCalibration, SkippedGroup
from .mapping import MAPPERS, REFINE_CHOICES, refine_intrinsics
from .mapping_retries import (
    InitialPair,
    MappingAttempt,
    RetryPlan,
    describe_attempts,
    map_with_retries,
)
from .mapping_runs import Refinement, global_mapping

#: Called with one line as each long stage starts (mapping, bundle adjustment).
StageCallback = Callable[[str], None]


@dataclass(frozen=True)
class ReconstructOptions:
    """Settings of :func:`reconstruct`; checked when built (:class:`CalibrationError`).

    Attributes:
        calibration: the calibration's options (method, prior, seed, grouping, ...); its
            ``seed`` also seeds the mapper. ``calibration.write`` is refused: ``write``
            below stores the estimate.
        mapper: ``incremental`` (pycolmap's incremental mapping, retried on hard motion) or
            ``global`` (pycolmap's global mapper, GLOMAP).
        refine: ``none`` keeps the estimate where the calibration determined it; ``ba``
            ends with the bundle adjustment of ``run`` (focal lengths and principal points
            with poses and points, and the distortion of models that have it).
        write: also store the estimate in the user's database (``<name>.bak`` first, as
            ``calibrate --write``) and move the images of each group onto its first
            camera there; without it the user's database is only read.
        workdir: where the temporary working folder (the database copy, the mapper's
            models) is made; None: the system's temporary folder. It is removed after.
        progress: a bar of registered images on stderr (and the calibration's bars).
    """

    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)
    mapper: str = "incremental"
    refine: str = "none"
    write: bool = False
    workdir: Path | None = None
    progress: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.calibration, CalibrationOptions):
            raise CalibrationError(
                f"calibration must be a CalibrationOptions, got {type(self.calibration).__name__}"
            )
        check_options(self.calibration)
        if self.calibration.write:
            raise CalibrationError(
                "calibration.write is not used by reconstruct: set ReconstructOptions(write=True)"
            )
        check_choice("mapper", self.mapper, MAPPERS)
        check_choice("refine", self.refine, REFINE_CHOICES)
        for name in ("write", "progress"):
            if not isinstance(getattr(self, name), bool):
                raise CalibrationError(f"{name} must be True or False")
        if self.workdir is not None and not Path(self.workdir).is_dir():
            raise CalibrationError(f"workdir {self.workdir} is not a folder")


def check_choice(name: str, value: object, choices: tuple[str, ...]) -> None:
    """CalibrationError unless ``value`` is one of ``choices`` (``name``: the option)."""
    if value not in choices:
        raise CalibrationError(f"unknown {name} {value!r} (choose from {', '.join(choices)})")


@dataclass
class Mapped:
    """What the mapping stage gave: the reconstruction and how it was made.

    ``mapping`` is the report's ``mapping`` object (mapper, what was refined while
    mapping, every attempt, the seeded pair, and a ``note`` when mapping was retried).
    """

    reconstruction: pycolmap.Reconstruction
    mapping: dict[str, Any]


def reconstruct(
    database: Path | str,
    images: Path | str | None = None,
    options: ReconstructOptions | None = None,
) -> tuple[pycolmap.Reconstruction, list[CameraCalibration]]:
    """Calibrate the database's cameras, then map it into a calibrated reconstruction.

    Args:
        database: a COLMAP database with verified matches (any tool's: COLMAP, hloc, ...).
        images: the image folder, only to colour the 3D points; None: uncoloured points
            (no image folder is needed).
        options: see :class:`ReconstructOptions` (default: msac-opt from the stored
            cameras, incremental mapping, the estimate kept).

    Returns:
        The largest model pycolmap's mapper made (in memory; each camera group is one
        shared ``pycolmap.Camera``, the group's first camera id), and the calibration's
        result per camera group (``result.fx``, ``result.std``, ...). A group the images
        give no estimate of (too few images or three-view tracks, a warning is logged)
        has no result: it is mapped from its stored cameras, as COLMAP would map it.

    Raises:
        CalibrationError: bad input, or no model (the message says which).
    """
    options = ReconstructOptions() if options is None else options
    if not isinstance(options, ReconstructOptions):
        raise CalibrationError(
            f"options must be a ReconstructOptions, got {type(options).__name__}"
        )
    database = Path(database)
    image_dir = checked_image_folder(images)
    contents = read_database(database)  # validated, one-line errors
    with tempfile.TemporaryDirectory(prefix="colmap-trifocal-", dir=options.workdir) as tmp:
        copy = Path(tmp) / "database.db"
        copy_database(database, copy, temporary=True)  # with what is still in its -wal
        calibrated = calibrate_for_mapping(contents, copy, options.calibration)
        if options.write:
            store_in_user_database(database, calibrated.calibrations)
        mapped = map_calibrated(copy, image_dir, Path(tmp) / "models", calibrated, options)
    if options.refine == "ba":
        refine_calibrated(mapped.reconstruction, calibrated)
    return mapped.reconstruction, calibrated.calibrations


def checked_image_folder(images: Path | str | None) -> Path | None:
    """The image folder as a Path (None stays None); CalibrationError if it is not a folder."""
    if images is None:
        return None
    folder = Path(images)
    if not folder.is_dir():
        raise CalibrationError(f"image folder not found: {folder}")
    return folder


@dataclass(frozen=True)
class Calibrated:
    """The calibrate stage of a mapping: each calibrated group's result, and the groups
    it skipped (fewer than 3 images, or no estimate from them: :class:`NoEstimate`)
    with their cameras as stored, from which mapping starts as COLMAP's would;
    ``models``: the camera models mapping starts from (the calibrated groups' as
    written for mapping, :meth:`.CameraCalibration.mapping_cameras`, and the stored ones)."""

    calibrations: list[CameraCalibration]
    skipped: list[SkippedGroup]
    stored: list[CameraInfo]
    models: list[str]

    def skipped_with_cameras(self) -> list[tuple[SkippedGroup, list[CameraInfo]]]:
        """Each skipped group with its cameras as stored."""
        by_id = {camera.camera_id: camera for camera in self.stored}
        return [(group, [by_id[c] for c in group.camera_ids]) for group in self.skipped]


def calibrate_for_mapping(
    contents: DatabaseContents,
    database: Path,
    options: CalibrationOptions,
    *,
    merge: bool = True,
) -> Calibrated:
    """Calibrate ``contents`` and prepare ``database`` (a copy this tool owns) for mapping.

    Every camera of each group gets the estimate as its starting intrinsics (also a group
    the images determined nothing of: the start is the best it has), and with ``merge``
    (mapping from scratch) the model that holds its lens
    (:meth:`.CameraCalibration.mapping_cameras`) and the images of each group are moved
    onto its first camera (:func:`merge_group_cameras`). Without ``merge`` (a given
    model's cameras) every camera keeps its stored model.

    A group the images give no estimate of is skipped with a warning (not an error: the
    mapper may still register its images) and keeps its stored cameras, whose focal
    length (and distortion) mapping then refines (:func:`refined_while_mapping`).
    """
    by_method, skipped = calibrate_groups(
        contents, options, (options.method,), skip_unestimated=True
    )
    calibrations = by_method[options.method]
    uncalibrated = [contents.cameras[c] for group in skipped for c in group.camera_ids]
    if merge:
        cameras = {i: c for r in calibrations for i, c in r.mapping_cameras().items()}
    else:
        cameras = updated_cameras(calibrations, determined_only=False)
    write_intrinsics(database, cameras, backup=False, change_models=merge)
    for camera_id, camera in cameras.items():
        stored = contents.cameras[camera_id]
        if camera.model != stored.model:
            logger.info(
                "camera %d mapped as %s: the tracks determine a lens %s cannot hold",
                camera_id,
                camera.model,
                stored.model,
            )
    if merge:
        merge_group_cameras(database, [list(c.camera_ids) for c in calibrations])
    models = [c.model for c in cameras.values()] + [c.model for c in uncalibrated]
    return Calibrated(calibrations, skipped, uncalibrated, models)


def store_in_user_database(database: Path, calibrations: list[CameraCalibration]) -> None:
    """``reconstruct(write=True)``: the estimate into the user's database (backup first, one
    transaction, read back), then each group's images onto its first camera. Nothing
    calibrated: the database stays as it was (no backup either)."""
    if not calibrations:
        logger.info("no camera calibrated: %s stays as it was", database)
        return
    written = write_intrinsics(database, updated_cameras(calibrations, determined_only=False))
    logger.info("stored the estimate in %s (backup: %s)", database, written)
    merge_group_cameras(database, [list(c.camera_ids) for c in calibrations])


def map_calibrated(
    database: Path,
    images: Path | None,
    output: Path,
    calibrated: Calibrated,
    options: ReconstructOptions,
    on_stage: StageCallback | None = None,
) -> Mapped:
    """Map ``database`` (prepared by :func:`calibrate_for_mapping`) with ``options.mapper``,
    holding what the tracks gave the calibration (:func:`refined_while_mapping`); the
    largest model and how it was made.

    ``output`` receives the mapper's models (one folder per attempt). Where no camera was
    calibrated and the mapper makes no model either, the CalibrationError says why the
    calibration skipped each group too.
    """
    calibrations = calibrated.calibrations
    refine = refined_while_mapping(calibrated)
    seed = options.calibration.seed
    announce(f"mapping (pycolmap {options.mapper})", on_stage)
    attempts: list[MappingAttempt] = []
    seeded: InitialPair | None = None
    try:
        if options.mapper == "global":
            reconstruction = global_mapping(
                database,
                images,
                output,
                refine_intrinsics_while_mapping=refine["focal_length"] or refine["principal_point"],
                seed=seed,
                refine_distortion=refine["distortion"],
            )
        else:
            reconstruction, attempts, seeded = map_with_retries(
                database,
                images,
                output,
                refine=Refinement(
                    refine["focal_length"], refine["principal_point"], refine["distortion"]
                ),
                plan=RetryPlan(
                    candidate_pairs=seed_candidate_pairs(calibrations),
                    known_focal_cameras=focal_estimated_cameras(calibrations),
                ),
                seed=seed,
                progress=options.progress,
            )
    except CalibrationError as exc:
        if calibrations or not calibrated.skipped:
            raise
        reasons = "; ".join(group.reason for group in calibrated.skipped)
        raise CalibrationError(
            f"{exc}; nor did the calibration estimate a camera: {reasons}"
        ) from exc
    mapping: dict[str, Any] = {
        "mapper": options.mapper,
        "refined_while_mapping": refine,
        "attempts": [asdict(a) for a in attempts],
        "seeded_pair": None if seeded is None else asdict(seeded),
    }
    retried = describe_attempts(attempts, seeded)
    if retried:
        logger.info(retried)
        mapping["note"] = retried
    return Mapped(reconstruction, mapping)


def refine_calibrated(
    reconstruction: pycolmap.Reconstruction,
    calibrated: Calibrated,
    on_stage: StageCallback | None = None,
) -> None:
    """The final bundle adjustment of ``run --refine ba``, in place: poses, points, focal
    lengths and principal points, and the distortion of camera models that have it.

    A PINHOLE camera whose calibration tied ``fy = fx`` (the images did not tell the two
    apart) keeps them equal: pycolmap's adjustment frees them apart, and took the temple
    ring's PINHOLE camera from 1.02 to 4.75 % (docs/hard_scenes.md, "What mapping
    refines")."""
    distortion = refined_while_mapping(calibrated)["distortion"]
    refined = "focal lengths, principal points" + (" and distortion" if distortion else "")
    announce(f"bundle adjustment of {refined}", on_stage)
    tied = tied_focal_cameras(calibrated.calibrations)
    refine_intrinsics(reconstruction, distortion=distortion, tied=tied)


#: A calibration's ``source`` of a value the tracks did not give: held at the start.
HELD_SOURCES = ("prior", "focal-search")


def refined_while_mapping(calibrated: Calibrated) -> dict[str, bool]:
    """Which intrinsics mapping refines: the focal length where a camera's calibration
    held it at its start (``source`` prior or focal-search) or a camera was not
    calibrated (its stored value, often COLMAP's guess), and the distortion of camera
    models that have it (also in the final bundle adjustment); never the principal
    point, as COLMAP's mapper. pycolmap's mapper refines each for every camera or for
    none.

    What the tracks gave, weakly determined or tied (fy = fx) included, is held: on the
    real scenes where it is weak (EuRoC, lego, the temple ring, KITTI) pycolmap's
    mapping of the same database ends further off than the calibration, and refining
    it while mapping took the ring's PINHOLE camera from 1.02 to 4.75 % (fx and fy
    apart); refining a principal point while mapping collapsed the KITTI drive
    (docs/hard_scenes.md, "What mapping refines").
    """
    calibrations, stored = calibrated.calibrations, calibrated.stored
    focal = bool(stored) or any(
        c.source.get(name) in HELD_SOURCES for c in calibrations for name in ("fx", "fy")
    )
    principal = False
    # TrifocalCalib undistorts with the stored parameters: a camera model with distortion
    # has it refined, as COLMAP's mapper does by default (held at COLMAP's k = 0, a real
    # lens biases every intrinsic; docs/limitations.md), and so has a lens the tracks
    # determined behind a model without it (mapped in the lens's model).
    distortion = any(model not in PINHOLE_MODELS for model in calibrated.models)
    return {"focal_length": focal, "principal_point": principal, "distortion": distortion}


def focal_estimated_cameras(calibrations: list[CameraCalibration]) -> list[int]:
    """Camera ids whose focal length the calibration estimated from the images (not held)."""
    return [int(camera_id) for c in calibrations if c.estimated["fx"] for camera_id in c.camera_ids]


#: Triplets of the calibration whose pairs are candidates for a seeded initial pair.
SEED_TRIPLETS = 8


def seed_candidate_pairs(
    calibrations: list[CameraCalibration], max_triplets: int = SEED_TRIPLETS
) -> list[tuple[int, int]]:
    """Image pairs of each camera's best triplets: candidates for a seeded initial pair.

    Best: the triplets the solve kept (``inlier``), by MSAC score (msac, msac-opt)
    and then inlier tracks; each contributes its three pairs (image ids).
    """
    pairs: list[tuple[int, int]] = []
    for calibration in calibrations:
        kept = [t for t in calibration.triplets if t.inlier] or list(calibration.triplets)
        kept.sort(
            key=lambda t: (t.score if t.score is not None else 0.0, t.num_inliers), reverse=True
        )
        for triplet in kept[:max_triplets]:
            a, b, c = (int(i) for i in triplet.image_ids)
            pairs += [(a, b), (b, c), (a, c)]
    return list(dict.fromkeys((min(p), max(p)) for p in pairs))


def announce(message: str, on_stage: StageCallback | None) -> None:
    """Announce a long stage in the log and to ``on_stage``."""
    logger.info(message)
    if on_stage is not None:
        on_stage(message)


def timed(seconds: dict[str, float], stage: str, began: float) -> None:
    """Record the wall seconds of ``stage`` since ``began`` (``time.perf_counter``)."""
    seconds[stage] = time.perf_counter() - began
