"""Make the images of a camera group use one camera id, in a database or a reconstruction.

:func:`merge_cameras` is the public helper: a ``pycolmap.Reconstruction`` gives a merged
copy (pycolmap cannot remove a camera from a reconstruction; the given one is left as it
is), a database file is changed in place after a backup ``<name>.bak``.

``run`` maps from its own copy of the database. When COLMAP's default extraction gave
every image its own camera, mapping and bundle adjustment would refine one set of
intrinsics per image; after grouping (:mod:`.camera_groups`) the images of a group are
moved to the group's first camera so that they share one set, as they physically do.
``run`` and ``reconstruct`` merge their working copy only, never the user's database.

Both schemas are handled: COLMAP 3.12+ (``rigs``, ``rig_sensors``, ``frames``,
``frame_data``: the frames of the moved images are attached to the first camera's rig,
the other cameras' single-sensor rigs are removed) and older ones (only ``images``
and ``cameras``).

The change is SQL in one transaction, checked after COMMIT. pycolmap's ``Database`` has
``update_image``, ``update_frame`` and ``update_rig`` but no way to delete one camera or
one rig (``clear_rigs`` removes every frame with them, its foreign keys cascade), and its
``DatabaseTransaction`` commits whatever was written when the block fails.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from contextlib import closing
from pathlib import Path
from typing import overload

import pycolmap

from ..common.errors import CalibrationError, interrupts_deferred
from ..common.log import logger
from .backup import back_up_locked
from .sqlite_files import check_sqlite_file, connect, database_error

#: ``sensor_type`` of a camera in COLMAP's rig tables.
_CAMERA_SENSOR = 0


@overload
def merge_cameras(
    target: pycolmap.Reconstruction, camera_ids: Sequence[int]
) -> pycolmap.Reconstruction: ...
@overload
def merge_cameras(target: Path | str, camera_ids: Sequence[int]) -> None: ...
def merge_cameras(
    target: pycolmap.Reconstruction | Path | str, camera_ids: Sequence[int]
) -> pycolmap.Reconstruction | None:
    """Make every image of ``camera_ids`` use the first of them; the others are removed.

    The cameras must be of one model and image size, each the only sensor of its rig
    (COLMAP's one camera per image; ``result.camera_ids`` of a calibration is such a
    group). The kept camera keeps its own params: write an estimate into it with
    ``result.apply`` (before or after).

    Args:
        target: a ``pycolmap.Reconstruction`` (not changed: the merged copy is returned,
            poses, points and unregistered images included), or the path of a COLMAP
            database (changed in place: a backup ``<name>.bak`` first, then one
            transaction, checked after it).
        camera_ids: the group; the first is the camera kept.

    Returns:
        The merged reconstruction, or None for a database.

    Raises:
        CalibrationError: an unknown camera id, cameras of different models or sizes, a
            camera of a multi-camera rig, an unusable database (missing, locked, ...), or
            another kind of target (a ``pycolmap.Database``: pass its path).
    """
    ids = _checked_ids(camera_ids)
    if isinstance(target, pycolmap.Reconstruction):
        return merge_reconstruction_cameras(target, ids)
    if isinstance(target, (str, Path)):
        check_sqlite_file(Path(target))
        merge_group_cameras(Path(target), [ids], backup=True)
        return None
    hint = " (pass its path: pycolmap cannot remove a camera)" * isinstance(
        target, pycolmap.Database
    )
    raise CalibrationError(
        "merge_cameras takes a pycolmap.Reconstruction or a database path, not "
        f"{type(target).__name__}{hint}"
    )


def _checked_ids(camera_ids: Sequence[int]) -> list[int]:
    """The camera ids as a list of ints (first kept); CalibrationError if not ids."""
    if isinstance(camera_ids, (str, bytes)) or not isinstance(camera_ids, Sequence):
        raise CalibrationError(f"camera_ids must be a list of camera ids, not {camera_ids!r}")
    if not camera_ids or not all(
        isinstance(c, int) and not isinstance(c, bool) for c in camera_ids
    ):
        raise CalibrationError(f"camera_ids must be a non-empty list of ints, not {camera_ids!r}")
    return list(dict.fromkeys(int(c) for c in camera_ids))


def merge_reconstruction_cameras(
    reconstruction: pycolmap.Reconstruction, ids: list[int]
) -> pycolmap.Reconstruction:
    """A copy of ``reconstruction`` whose images of ``ids`` all use ``ids[0]`` (their frames
    in its rig), the other cameras and their single-camera rigs left out."""
    keep, others = ids[0], set(ids[1:])
    _check_reconstruction_group(reconstruction, ids)
    merged = pycolmap.Reconstruction()
    for camera in reconstruction.cameras.values():
        if camera.camera_id not in others:
            merged.add_camera(camera)
    rig_of_camera: dict[int, int] = {}
    for rig in reconstruction.rigs.values():
        reference = rig.ref_sensor_id
        if reference.type == pycolmap.SensorType.CAMERA:
            rig_of_camera[int(reference.id)] = int(rig.rig_id)
        if not (reference.type == pycolmap.SensorType.CAMERA and reference.id in others):
            merged.add_rig(rig)
    removed_rigs = {rig_of_camera[c] for c in others}
    for frame in reconstruction.frames.values():
        rig_id = rig_of_camera[keep] if frame.rig_id in removed_rigs else frame.rig_id
        merged.add_frame(_moved_frame(frame, rig_id, keep, others))
    for image in reconstruction.images.values():
        camera_id = keep if image.camera_id in others else image.camera_id
        merged.add_image(
            pycolmap.Image(
                name=image.name,
                points2D=image.points2D,
                camera_id=camera_id,
                image_id=image.image_id,
                frame_id=image.frame_id,
            )
        )
    for point_id, point in reconstruction.points3D.items():
        merged.add_point3D_with_id(point_id, point)
    return merged


def _moved_frame(frame: pycolmap.Frame, rig_id: int, keep: int, others: set[int]) -> pycolmap.Frame:
    """A copy of ``frame`` in rig ``rig_id``, its images of ``others`` on camera ``keep``."""
    moved = pycolmap.Frame()
    moved.frame_id = frame.frame_id
    moved.rig_id = rig_id
    for data in frame.data_ids:
        sensor = data.sensor_id
        if sensor.type == pycolmap.SensorType.CAMERA and sensor.id in others:
            sensor = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, keep)
        moved.add_data_id(pycolmap.data_t(sensor, data.id))
    if frame.has_pose():
        moved.rig_from_world = frame.rig_from_world
    return moved


def _check_reconstruction_group(reconstruction: pycolmap.Reconstruction, ids: list[int]) -> None:
    """CalibrationError unless every id is a camera of the reconstruction, all of one model
    and size, each the only sensor of its rig."""
    missing = [c for c in ids if not reconstruction.exists_camera(c)]
    if missing:
        raise CalibrationError(
            f"the reconstruction has no camera {missing[0]} (it has camera ids "
            f"{sorted(reconstruction.cameras)[:10]})"
        )
    kinds = {
        (c.model.name, int(c.width), int(c.height)) for c in (reconstruction.camera(i) for i in ids)
    }
    if len(kinds) > 1:
        raise CalibrationError(f"cameras {ids} differ in model or image size: {sorted(kinds)}")
    shared = {
        int(sensor.id)
        for rig in reconstruction.rigs.values()
        if rig.num_sensors() > 1
        for sensor in rig.sensor_ids()
        if sensor.type == pycolmap.SensorType.CAMERA
    }
    if shared & set(ids):
        raise CalibrationError(f"camera {min(shared & set(ids))} is a sensor of a multi-camera rig")


def merge_group_cameras(database: Path, groups: list[list[int]], *, backup: bool = False) -> int:
    """Point every image of each group at the group's first camera; drop the others.

    Args:
        database: a COLMAP database; without ``backup`` one this tool owns (a workspace
            copy).
        groups: camera ids per group (first = the camera kept). The cameras of a
            group must be of one model and size and not sensors of a multi-camera rig
            (grouping never does that; checked).
        backup: copy the database to ``<name>.bak`` (``.bak1``, ... if taken) first, under
            the write lock (removed again if the merge fails).

    Returns:
        The number of camera ids removed.

    Raises:
        CalibrationError: the database could not be changed (locked, corrupt, a camera
            without a rig), or does not show the change afterwards.
    """
    database = Path(database)
    merges = [(ids[0], [c for c in ids[1:] if c != ids[0]]) for ids in groups]
    merges = [(keep, others) for keep, others in merges if others]
    if not merges:
        return 0
    removed = [camera for _, others in merges for camera in others]
    try:
        with closing(connect(database, "mode=rw")) as con:
            tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master")}
            rigs = {"rigs", "rig_sensors", "frames", "frame_data"} <= tables
            con.execute("BEGIN IMMEDIATE")
            _merge_and_commit(con, merges, database, rigs=rigs, backup=backup)
            _check_merged(con, removed, database, rigs=rigs)
    except sqlite3.Error as exc:
        raise database_error(exc, database, "merge the cameras of") from None
    logger.info(
        "%s: %d camera ids merged into %d group camera(s)", database, len(removed), len(merges)
    )
    return len(removed)


def _merge_and_commit(
    con: sqlite3.Connection,
    merges: list[tuple[int, list[int]]],
    database: Path,
    *,
    rigs: bool,
    backup: bool,
) -> None:
    """Inside the caller's ``BEGIN IMMEDIATE``: check, back up, move, COMMIT (SIGINT,
    SIGTERM, SIGHUP wait while COMMIT runs). Anything that ends it before COMMIT removes
    the backup (while the lock is held) and rolls back."""
    made = None
    try:
        _check_database_groups(con, merges, rigs=rigs)
        made = back_up_locked(database) if backup else None
        for keep, others in merges:
            marks = ",".join("?" * len(others))
            con.execute(
                f"UPDATE images SET camera_id = ? WHERE camera_id IN ({marks})", (keep, *others)
            )
            if rigs:
                _move_frames(con, keep, others, marks)
            con.execute(f"DELETE FROM cameras WHERE camera_id IN ({marks})", others)
        with interrupts_deferred():
            con.execute("COMMIT")
    except BaseException:
        if con.in_transaction:
            if made is not None:
                made.remove()
            con.execute("ROLLBACK")
        raise


def _check_database_groups(
    con: sqlite3.Connection, merges: list[tuple[int, list[int]]], *, rigs: bool
) -> None:
    """CalibrationError unless each group's cameras exist, share model and size, and are
    each the only sensor of their rig."""
    kinds = {
        int(row[0]): tuple(row[1:])
        for row in con.execute("SELECT camera_id, model, width, height FROM cameras")
    }
    in_rigs: set[int] = set()
    if rigs:
        in_rigs = {
            int(row[0])
            for row in con.execute(
                "SELECT sensor_id FROM rig_sensors WHERE sensor_type = ? UNION "
                "SELECT ref_sensor_id FROM rigs WHERE ref_sensor_type = ? AND rig_id IN "
                "(SELECT rig_id FROM rig_sensors)",
                (_CAMERA_SENSOR, _CAMERA_SENSOR),
            )
        }
    for keep, others in merges:
        ids = [keep, *others]
        missing = [c for c in ids if c not in kinds]
        if missing:
            raise CalibrationError(f"camera {missing[0]} is not in the database")
        if len({kinds[c] for c in ids}) > 1:
            raise CalibrationError(f"cameras {ids} differ in model or image size")
        if in_rigs & set(ids):
            raise CalibrationError(
                f"camera {min(in_rigs & set(ids))} is a sensor of a multi-camera rig"
            )


def _check_merged(
    con: sqlite3.Connection, removed: list[int], database: Path, *, rigs: bool
) -> None:
    """Raise unless no image, camera or frame refers to a removed camera any more."""
    marks = ",".join("?" * len(removed))
    queries = [
        f"SELECT COUNT(*) FROM images WHERE camera_id IN ({marks})",
        f"SELECT COUNT(*) FROM cameras WHERE camera_id IN ({marks})",
    ]
    if rigs:
        queries.append(
            f"SELECT COUNT(*) FROM frame_data WHERE sensor_type = {_CAMERA_SENSOR} "
            f"AND sensor_id IN ({marks})"
        )
    for query in queries:
        if con.execute(query, removed).fetchone()[0]:
            raise CalibrationError(f"verification failed after merging the cameras of {database}")


def _move_frames(con: sqlite3.Connection, keep: int, others: list[int], marks: str) -> None:
    """Attach the frames of ``others``' images to ``keep``'s rig; remove their rigs."""
    row = con.execute(
        "SELECT rig_id FROM rig_sensors WHERE sensor_type = ? AND sensor_id = ? UNION "
        "SELECT rig_id FROM rigs WHERE ref_sensor_type = ? AND ref_sensor_id = ?",
        (_CAMERA_SENSOR, keep, _CAMERA_SENSOR, keep),
    ).fetchone()
    if row is None:
        raise CalibrationError(f"camera {keep} has no rig")
    rig = int(row[0])
    old_rigs = [
        int(r[0])
        for r in con.execute(
            f"SELECT rig_id FROM rigs WHERE ref_sensor_type = ? AND ref_sensor_id IN ({marks})",
            (_CAMERA_SENSOR, *others),
        )
    ]
    con.execute(
        f"UPDATE frames SET rig_id = ? WHERE frame_id IN (SELECT frame_id FROM frame_data "
        f"WHERE sensor_type = ? AND sensor_id IN ({marks}))",
        (rig, _CAMERA_SENSOR, *others),
    )
    con.execute(
        f"UPDATE frame_data SET sensor_id = ? WHERE sensor_type = ? AND sensor_id IN ({marks})",
        (keep, _CAMERA_SENSOR, *others),
    )
    if old_rigs:
        rig_marks = ",".join("?" * len(old_rigs))
        con.execute(f"DELETE FROM rig_sensors WHERE rig_id IN ({rig_marks})", old_rigs)
        con.execute(f"DELETE FROM rigs WHERE rig_id IN ({rig_marks})", old_rigs)
