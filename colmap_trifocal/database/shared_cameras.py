"""Make the images of a camera group use one camera id (in a workspace copy of a database).

``run`` maps from its own copy of the database. When COLMAP's default extraction gave
every image its own camera, mapping and bundle adjustment would refine one set of
intrinsics per image; after grouping (:mod:`.camera_groups`) the images of a group are
moved to the group's first camera so that they share one set, as they physically do.
Never applied to the user's database.

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
from contextlib import closing
from pathlib import Path

from ..common.errors import CalibrationError
from ..common.log import logger
from .sqlite_files import connect, database_error

#: ``sensor_type`` of a camera in COLMAP's rig tables.
_CAMERA_SENSOR = 0


def merge_group_cameras(database: Path, groups: list[list[int]]) -> int:
    """Point every image of each group at the group's first camera; drop the others.

    Args:
        database: a COLMAP database this tool owns (a workspace copy).
        groups: camera ids per group (first = the camera kept). The cameras of a
            group must not be sensors of a multi-camera rig (grouping never does that).

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
            with con:  # COMMIT, or ROLLBACK if anything (an interrupt too) ends the block
                for keep, others in merges:
                    marks = ",".join("?" * len(others))
                    con.execute(
                        f"UPDATE images SET camera_id = ? WHERE camera_id IN ({marks})",
                        (keep, *others),
                    )
                    if rigs:
                        _move_frames(con, keep, others, marks)
                    con.execute(f"DELETE FROM cameras WHERE camera_id IN ({marks})", others)
            _check_merged(con, removed, rigs, database)
    except sqlite3.Error as exc:
        raise database_error(exc, database, "merge the cameras of") from None
    logger.info(
        "%s: %d camera ids merged into %d group camera(s)", database, len(removed), len(merges)
    )
    return len(removed)


def _check_merged(con: sqlite3.Connection, removed: list[int], rigs: bool, database: Path) -> None:
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
