"""Where a camera group's estimate can be written: which of its ids a target holds, and
the write into a database (an open ``pycolmap.Database``, or a file through the safe write).

A group's cameras are in a target either all of them (COLMAP's one camera per image, each
id kept) or only the group's first (the group merged into one shared camera by
:func:`.shared_cameras.merge_cameras` or ``reconstruct``); anything else is another
database's cameras. Every camera is checked before any is written.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Collection, Mapping, Sequence
from contextlib import closing
from pathlib import Path

import pycolmap

from ..common.errors import CalibrationError
from .cameras import CameraInfo
from .sqlite_files import check_sqlite_file, connect, database_error, sidecar
from .writing import write_intrinsics


def group_ids_held(ids: Sequence[int], held: Collection[int], where: str) -> list[int]:
    """The ids of the group ``ids`` (first = the group's camera) that ``where`` holds, when
    it holds all of them or only the first (a merged group); CalibrationError otherwise."""
    present = [c for c in ids if c in held]
    if present == list(ids) or present == [ids[0]]:
        return present
    missing = next(c for c in ids if c not in held)
    shown = sorted(held)[:10]
    raise CalibrationError(
        f"{where} has no camera {missing} (it has camera ids {shown}): is it from this database?"
    )


def check_same_camera(
    camera_id: int, target: pycolmap.Camera, camera: CameraInfo, where: str
) -> None:
    """CalibrationError unless ``target`` (the target's camera) has ``camera``'s model and size."""
    if (target.model.name, int(target.width), int(target.height)) != (
        camera.model,
        camera.width,
        camera.height,
    ):
        raise CalibrationError(
            f"camera {camera_id} of {where} is a {target.model.name} "
            f"{target.width}x{target.height}, the calibrated one a {camera.model} "
            f"{camera.width}x{camera.height}: is it from this database?"
        )


def write_to_open_database(
    database: pycolmap.Database, cameras: Mapping[int, CameraInfo], group: Sequence[int]
) -> list[int]:
    """Write the group's cameras' params into an open ``pycolmap.Database`` (one transaction).

    Returns the camera ids written. Raises CalibrationError for a closed database, a
    missing id (see :func:`group_ids_held`) or another model or size.
    """
    where = "the database"
    try:
        held = [c for c in group if database.exists_camera(c)]
        targets = {c: database.read_camera(c) for c in group_ids_held(group, held, where)}
    except (ValueError, RuntimeError) as exc:
        raise CalibrationError(f"cannot read the pycolmap.Database (closed?): {exc}") from None
    for camera_id, target in targets.items():
        check_same_camera(camera_id, target, cameras[camera_id], where)
    with pycolmap.DatabaseTransaction(database):
        for camera_id, target in targets.items():
            target.params = cameras[camera_id].params.tolist()
            database.update_camera(target)
    return sorted(targets)


def write_to_database_file(
    path: Path, cameras: Mapping[int, CameraInfo], group: Sequence[int]
) -> list[int]:
    """Write the group's cameras' params into the database file at ``path``: a backup
    ``<name>.bak`` first, one transaction, read back (:func:`.writing.write_intrinsics`).

    Returns the camera ids written.
    """
    path = Path(path)
    if path.is_dir():
        raise CalibrationError(
            f"{path} is a folder: apply takes a database file, a pycolmap.Database or a "
            "pycolmap.Reconstruction (pycolmap.Reconstruction(path) reads a model folder)"
        )
    check_sqlite_file(path)
    # Without a -wal the main file holds everything: read it as immutable, which leaves no
    # -wal/-shm files behind (as the snapshot does).
    query = "mode=ro" if sidecar(path, "-wal").exists() else "mode=ro&immutable=1"
    try:
        with closing(connect(path, query)) as con:
            held = {int(row[0]) for row in con.execute("SELECT camera_id FROM cameras")}
    except sqlite3.Error as exc:
        raise database_error(exc, path, "read") from None
    ids = group_ids_held(group, held, f"the database {path}")
    write_intrinsics(path, {c: cameras[c] for c in ids})
    return ids
