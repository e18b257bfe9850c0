"""Calibrate every camera of a COLMAP database: the public entry point.

``calibrate_database(path, options)`` reads the database (never changing it),
groups its camera ids into physical cameras (:mod:`..database.camera_groups`;
COLMAP's default gives one camera id per image), then for each group with at
least 3 images: undistorts each image's keypoints with its own camera's stored
distortion, selects triplets among the group's images, estimates one robust
tensor per triplet, and solves for (fx, fy, cx, cy) with the chosen method.
Groups with fewer images are skipped (reported, not an error, while another
group calibrates). With ``options.write`` the estimates are stored in every
camera of each group (backup first, one transaction).

``calibrate_reconstruction(model, options)`` does the same from a COLMAP
reconstruction's tracks (:mod:`..database.from_reconstruction`); its results also
carry the reconstruction's own intrinsics (``reference``) and are written back into
a reconstruction with ``result.apply(reconstruction)``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError, NoEstimate
from ..common.log import logger
from ..common.parallel import single_threaded_libraries
from ..database.camera_groups import CameraGroup, group_cameras
from ..database.cameras import CameraInfo
from ..database.from_reconstruction import (
    contents_from_reconstruction,
    grouping_cameras,
    model_intrinsics,
    read_reconstruction,
)
from ..database.snapshot import DatabaseContents, read_database
from ..database.writing import write_intrinsics
from .api_checks import (
    checked_contents,
    checked_grouping,
    checked_methods,
    checked_options,
    checked_path,
)
from .inputs.prior import default_guess, parse_prior, start_source
from .options import METHODS, CalibrationOptions, check_options
from .pipeline import calibrate_camera
from .results import CameraCalibration, GroupCalibration, SkippedGroup

#: The public API (``colmap_trifocal.__all__``) and the names the command line takes from here.
__all__ = [
    "METHODS",
    "CalibrationOptions",
    "CameraCalibration",
    "GroupCalibration",
    "SkippedGroup",
    "add_read_seconds",
    "calibrate_contents",
    "calibrate_contents_methods",
    "calibrate_database",
    "calibrate_groups",
    "calibrate_reconstruction",
    "check_options",
    "default_guess",
    "parse_prior",
    "plan_groups",
    "read_contents",
    "updated_cameras",
    "write_calibrations",
]


def calibrate_database(
    path: Path | str, options: CalibrationOptions | None = None
) -> list[CameraCalibration]:
    """Estimate the intrinsics of the cameras of a COLMAP database.

    Args:
        path: the database; opened read-only unless ``options.write``.
        options: method, prior, seed, ... (defaults: msac-opt from the stored cameras).

    Returns:
        One result per calibrated camera, ordered by camera id.

    Raises:
        CalibrationError: bad input (see the message).
    """
    options = checked_options(options)
    path = checked_path(path, "the database path")
    contents, read_seconds = read_contents(path)
    results = calibrate_contents(contents, options)
    results = add_read_seconds(results, read_seconds)
    if options.write:
        write_calibrations(path, results)
    return results


def calibrate_reconstruction(
    reconstruction: pycolmap.Reconstruction | Path | str,
    options: CalibrationOptions | None = None,
) -> list[CameraCalibration]:
    """Estimate the intrinsics of a COLMAP reconstruction's cameras from its tracks.

    Two observations of one 3D point in two registered images are a match; the 3D
    points and poses are not used (:mod:`..database.from_reconstruction`). Without a
    prior the start is the reconstruction's camera, and its distortion undistorts the
    keypoints. Under ``group="auto"`` camera ids of one model and size whose focal
    lengths agree within :data:`..database.from_reconstruction.MODEL_FOCAL_TOLERANCE`
    are one camera (bundle adjustment refines each id on its own).

    Args:
        reconstruction: a ``pycolmap.Reconstruction`` (not changed), or a model folder
            (``sparse/0``, binary or text).
        options: as for :func:`calibrate_database`; ``write`` is refused (write the
            estimate into a reconstruction with ``result.apply(reconstruction)``).

    Returns:
        One result per calibrated camera group, ordered by camera id, each with
        ``reference``: the reconstruction's own (fx, fy, cx, cy), the mean over the group.

    Raises:
        CalibrationError: bad input (see the message).
    """
    return reconstruction_groups(reconstruction, options)[0]


def reconstruction_groups(
    reconstruction: pycolmap.Reconstruction | Path | str,
    options: CalibrationOptions | None = None,
) -> tuple[list[CameraCalibration], list[SkippedGroup]]:
    """:func:`calibrate_reconstruction`'s results, and the groups it skipped."""
    options = checked_options(options)
    if options.write:
        raise CalibrationError(
            "options.write stores estimates in a database; write them into a "
            "reconstruction with result.apply(reconstruction)"
        )
    clock = time.perf_counter()
    if not isinstance(reconstruction, pycolmap.Reconstruction):
        what = "reconstruction (a pycolmap.Reconstruction or a model folder)"
        reconstruction = read_reconstruction(checked_path(reconstruction, what))
    contents = contents_from_reconstruction(reconstruction)
    read_seconds = time.perf_counter() - clock
    grouping = grouping_cameras(contents.cameras) if options.group == "auto" else None
    methods = (options.method,)
    by_method, skipped = calibrate_groups(contents, options, methods, grouping=grouping)
    results = by_method[options.method]
    results = [
        replace(
            result,
            provenance=replace(result.provenance, reference=model_intrinsics(result.group_cameras)),
        )
        for result in add_read_seconds(results, read_seconds)
    ]
    return results, skipped


def read_contents(path: Path | str) -> tuple[DatabaseContents, float]:
    """The database's snapshot (:func:`.database.read_database`) and the wall seconds it took."""
    clock = time.perf_counter()
    contents = read_database(Path(path))
    return contents, time.perf_counter() - clock


def add_read_seconds(
    results: Sequence[CameraCalibration], seconds: float
) -> list[CameraCalibration]:
    """The results with reading the database (shared by every group) counted in each
    one's ``read`` stage."""
    timed = []
    for result in results:
        stages = dict(result.stage_seconds)
        stages["read"] = round(stages.get("read", 0.0) + seconds, 4)
        stages["total"] = round(stages.get("total", 0.0) + seconds, 4)
        timing = replace(result.timing, seconds=result.seconds + seconds, stage_seconds=stages)
        timed.append(replace(result, timing=timing))
    return timed


def updated_cameras(
    results: Sequence[CameraCalibration], *, determined_only: bool = True
) -> dict[int, CameraInfo]:
    """camera_id -> stored camera with its group's estimate, for every camera of every group.

    Distortion is kept per camera, or estimated where the stored one is 0. With
    ``determined_only`` a group the images determined nothing of is left out (writing
    the prior back would record a guess).
    """
    updated: dict[int, CameraInfo] = {}
    for r in results:
        if not determined_only or r.determined_anything:
            updated.update(r.updated_cameras())
    return updated


def tied_focal_cameras(results: Sequence[CameraCalibration]) -> list[int]:
    """The camera ids of every group whose calibration tied fy to fx (``source["fy"]``
    ``tied``: the images did not tell the two apart), for a bundle adjustment to keep."""
    return [
        camera_id for r in results if r.source.get("fy") == "tied" for camera_id in r.camera_ids
    ]


def write_calibrations(path: Path | str, results: Sequence[CameraCalibration]) -> int:
    """Store the estimates in the database at ``path`` (backup first, one transaction).

    Every camera id of a group gets the group's estimate. A group the images
    determined nothing of keeps its stored parameters: writing the prior back
    would record a guess as a calibration. Distortion is kept, per camera, except
    where the stored one is 0 and the tracks showed some (:mod:`intrinsics.lens.distortion`).

    Returns:
        The number of cameras written.

    Raises:
        CalibrationError: see :func:`.database.write_intrinsics`.
    """
    updated = updated_cameras(results)
    if updated:
        backup = write_intrinsics(Path(path), updated)
        logger.info("wrote %d camera(s) to %s (backup: %s)", len(updated), path, backup)
    return len(updated)


def calibrate_contents(
    contents: DatabaseContents, options: CalibrationOptions
) -> list[CameraCalibration]:
    """Calibrate the cameras of already-read database contents (see :func:`calibrate_database`)."""
    options = check_options(options)
    return calibrate_contents_methods(contents, options, (options.method,))[options.method]


def calibrate_contents_methods(
    contents: DatabaseContents, options: CalibrationOptions, methods: tuple[str, ...]
) -> dict[str, list[CameraCalibration]]:
    """Several methods on the same contents; the trifocal variants share one set of tensors.

    Each result's ``seconds`` is what that method alone would take (the shared
    focal search and tensors plus its own solve). ``options.method`` is ignored.
    One result per calibrated group; skipped groups are only logged here (see
    :func:`calibrate_groups`).
    """
    return calibrate_groups(contents, options, methods)[0]


def plan_groups(
    contents: DatabaseContents,
    options: CalibrationOptions,
    grouping: Mapping[int, CameraInfo] | None = None,
    *,
    skip_unestimated: bool = False,
) -> tuple[list[CameraGroup], list[SkippedGroup]]:
    """The groups to calibrate (``options.group``, ``options.camera_ids``), and those skipped.

    ``grouping``: the cameras the grouping compares instead of ``contents.cameras``
    (a reconstruction's, see :func:`..database.from_reconstruction.grouping_cameras`).
    A group with fewer than 3 images is skipped. Raises CalibrationError for an
    unknown camera id, and NoEstimate when no group has 3 images (unless
    ``skip_unestimated``: every group is then returned as skipped).
    """
    groups = group_cameras(
        contents.cameras if grouping is None else grouping,
        contents.image_camera,
        options.group,
        contents.rig_sensor_cameras,
    )
    if options.camera_ids is not None:
        missing = sorted(set(options.camera_ids) - set(contents.cameras))
        if missing:
            raise CalibrationError(f"camera id {missing[0]} is not in the database")
        wanted = set(options.camera_ids)
        groups = [g for g in groups if wanted & set(g.camera_ids)]
        if not groups:
            raise CalibrationError(f"camera {min(wanted)} has no images")
    ready = [g for g in groups if len(g.image_ids) >= 3]
    skipped = [
        SkippedGroup(list(g.camera_ids), len(g.image_ids), _images(len(g.image_ids)))
        for g in groups
        if len(g.image_ids) < 3
    ]
    if not ready and not skip_unestimated:
        if options.camera_ids is not None and len(groups) == 1:
            (group,) = groups
            raise NoEstimate(
                f"{group.describe()} has {_images(len(group.image_ids))}; at least 3 are needed"
            )
        raise NoEstimate(
            "no camera has at least 3 images (grouped with --group "
            f"{options.group}: {len(groups)} group(s) of at most "
            f"{max((len(g.image_ids) for g in groups), default=0)} image(s))"
        )
    return ready, skipped


def _images(count: int) -> str:
    """``1 image``, ``2 images``."""
    return f"{count} image" if count == 1 else f"{count} images"


def calibrate_groups(
    contents: DatabaseContents,
    options: CalibrationOptions,
    methods: tuple[str, ...],
    grouping: Mapping[int, CameraInfo] | None = None,
    *,
    skip_unestimated: bool = False,
) -> tuple[dict[str, list[CameraCalibration]], list[SkippedGroup]]:
    """Calibrate every group with each of ``methods``; also return the skipped groups.

    ``grouping``: see :func:`plan_groups`.

    With several groups, one that cannot be calibrated (no triplet, no valid
    estimate, ...) is skipped with the reason while the others calibrate; when none
    calibrates, the first group's error is raised. With ``skip_unestimated`` a group
    the images give no estimate of (:class:`NoEstimate`) is skipped even when it is the
    only one, and the results may be empty (mapping then starts from the stored
    cameras, :func:`..reconstruction.pipeline.calibrate_for_mapping`).
    """
    contents = checked_contents(contents)
    options = check_options(options)
    methods = checked_methods(methods)
    grouping = checked_grouping(grouping, contents)
    groups, skipped = plan_groups(contents, options, grouping, skip_unestimated=skip_unestimated)
    results: dict[str, list[CameraCalibration]] = {m: [] for m in methods}
    first_error: CalibrationError | None = None
    for group in groups:
        cameras = [contents.cameras[c] for c in group.camera_ids]
        if len(group.camera_ids) > 1:
            logger.info(
                "%s: %d images with shared intrinsics", group.describe(), len(group.image_ids)
            )
        try:
            with single_threaded_libraries():
                per_method = calibrate_camera(
                    contents, cameras[0], list(group.image_ids), options, methods
                )
        except CalibrationError as exc:
            unestimated = skip_unestimated and isinstance(exc, NoEstimate)
            if len(groups) == 1 and not unestimated:
                raise
            if not unestimated:
                first_error = first_error or exc
            logger.warning("%s skipped: %s", group.describe(), exc)
            skipped.append(SkippedGroup(list(group.camera_ids), len(group.image_ids), str(exc)))
            continue
        source = start_source(cameras[0], options.start_options)
        for method, result in per_method.items():
            results[method].append(
                replace(
                    result,
                    camera_ids=[c.camera_id for c in cameras],
                    provenance=replace(
                        result.provenance, start_source=source, group_cameras=list(cameras)
                    ),
                )
            )
    if not results[methods[0]] and first_error is not None:
        raise first_error
    for skip in skipped:
        logger.warning("%s", skip.message())
    skipped.sort(key=lambda g: g.camera_id)
    return results, skipped
