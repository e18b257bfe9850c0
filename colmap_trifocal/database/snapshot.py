"""Read a COLMAP database without touching it: a snapshot, read by pycolmap, checked.

The user's file is copied once (:func:`.sqlite_files.copy_database`: one consistent read,
the ``-wal`` included, no companion files left behind) into a temporary folder, leaving the
blobs of descriptors and raw matches empty (the calibration never reads them, and they are
most of a real database); pycolmap only ever opens that snapshot.

Conventions
-----------
* Image pairs are keyed ``(id1, id2)`` with ``id1 < id2``. ``matches[(id1, id2)][:, 0]``
  indexes ``keypoints[id1]`` and ``[:, 1]`` indexes ``keypoints[id2]``.
* COLMAP stores a pair as ``pair_id = 2147483647 * id1 + id2`` (``MAX_NUM_IMAGES``).
* Keypoints are raw (distorted) pixel coordinates as stored by COLMAP; the centre of the
  top-left pixel is at ``(0.5, 0.5)``.
* ``fundamentals[(id1, id2)] = F`` satisfies ``x2^T F x1 = 0`` for homogeneous pixel
  coordinates ``x1`` in image ``id1`` and ``x2`` in image ``id2``. This is COLMAP's
  convention for the pair returned by ``pycolmap.pair_id_to_image_pair(pair_id)`` (checked
  numerically in the tests). COLMAP estimates F on raw keypoints; when only an essential
  matrix is stored (``CALIBRATED`` geometries) F is derived as ``K2^-T E K1^-1`` with the
  cameras' pinhole ``K``, which holds for undistorted pixels (exact for pinhole cameras).
"""

from __future__ import annotations

import sqlite3
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.log import logger
from .cameras import CameraInfo
from .sqlite_files import connect, copy_database, database_error

#: Tables whose blobs the snapshot leaves empty: the calibration never reads them.
SKIPPED_TABLES = frozenset({"descriptors", "matches"})
MIN_IMAGES = 3
#: A verified pair whose matched keypoints moved less than this (median, pixels) is the
#: same picture twice (or a camera that did not move): no baseline, nothing to calibrate
#: from, and its triplets give tensors that fit anything. It is left out.
DUPLICATE_DISPLACEMENT_PX = 1.0
#: The duplicate test uses this many matches of a pair, evenly spaced (its median).
DUPLICATE_SAMPLE = 32
#: COLMAP's ``kMaxNumImages``: ``pair_id = MAX_NUM_IMAGES * id1 + id2``, image ids below it.
MAX_NUM_IMAGES = 2**31 - 1
#: Column counts of COLMAP's keypoint blobs: x, y [, scale, orientation | a11, a12, a21, a22].
KEYPOINT_COLUMNS = (2, 4, 6)

_Config = pycolmap.TwoViewGeometryConfiguration
#: Two-view geometries whose inliers are not used: failed or watermark-only pairs.
_EXCLUDED_CONFIGS = frozenset({int(_Config.DEGENERATE), int(_Config.WATERMARK)})
#: Configurations for which a stored essential matrix may stand in for a missing F.
_CALIBRATED_CONFIGS = frozenset({int(_Config.CALIBRATED), int(_Config.CALIBRATED_RIG)})

Pair = tuple[int, int]


@dataclass
class DatabaseContents:
    """Everything the calibration needs from a COLMAP database (see module conventions).

    Attributes:
        cameras: camera_id -> camera (params as stored).
        image_names: image_id -> image name.
        image_camera: image_id -> camera_id.
        keypoints: image_id -> (n, 2) float64 raw pixel coordinates ``(x, y)``.
        matches: (id1, id2), id1 < id2 -> (m, 2) int32 keypoint indices of the verified
            inlier matches (m >= 1).
        fundamentals: only with ``read_database(..., fundamentals=True)``: (id1, id2) ->
            3x3 float64 F with ``x2^T F x1 = 0`` (pixels), for the
            matched pairs that have a usable F.
        rig_sensor_cameras: camera ids that are one of several camera sensors of a rig
            (COLMAP 3.12+ ``rigs`` table; pycolmap gives a database without it one rig
            per camera): different physical cameras, never grouped together.
    """

    cameras: dict[int, CameraInfo] = field(default_factory=dict)
    image_names: dict[int, str] = field(default_factory=dict)
    image_camera: dict[int, int] = field(default_factory=dict)
    keypoints: dict[int, np.ndarray] = field(default_factory=dict)
    matches: dict[Pair, np.ndarray] = field(default_factory=dict)
    fundamentals: dict[Pair, np.ndarray] = field(default_factory=dict)
    rig_sensor_cameras: set[int] = field(default_factory=set)


def _keypoints_xy(raw: np.ndarray) -> np.ndarray:
    """First two columns (x, y) of COLMAP keypoints as a contiguous (n, 2) float64 array."""
    arr = np.asarray(raw)
    if arr.size == 0:
        return np.zeros((0, 2), dtype=np.float64)
    return np.ascontiguousarray(arr.reshape(arr.shape[0], -1)[:, :2], dtype=np.float64)


def _usable(matrix: np.ndarray | None) -> np.ndarray | None:
    """A finite, nonzero 3x3 float64 matrix, or None."""
    if matrix is None:
        return None
    arr = np.asarray(matrix, dtype=np.float64)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)) or not np.any(arr):
        return None
    return arr.copy()


def _pair_fundamental(
    tvg: pycolmap.TwoViewGeometry, contents: DatabaseContents, id1: int, id2: int
) -> np.ndarray | None:
    """F of a two-view geometry (image 1 -> image 2), from F or else from E; None if neither."""
    camera1 = contents.cameras.get(contents.image_camera[id1])
    camera2 = contents.cameras.get(contents.image_camera[id2])
    fundamental = _usable(tvg.F)
    if fundamental is not None or int(tvg.config) not in _CALIBRATED_CONFIGS:
        return fundamental
    essential = _usable(tvg.E)
    if essential is None or camera1 is None or camera2 is None:
        return None
    return np.linalg.inv(camera2.K).T @ essential @ np.linalg.inv(camera1.K)


def _verified_pairs(
    pair_ids: list[int],
    geometries: list[pycolmap.TwoViewGeometry],
    contents: DatabaseContents,
    path: Path,
    *,
    fundamentals: bool,
) -> Counter[str]:
    """Fill ``contents.matches`` (and, if asked, ``contents.fundamentals``).

    Per pair only what cannot wait is done in Python; the duplicate test (median
    displacement of ``DUPLICATE_SAMPLE`` evenly spaced matches) runs on all pairs at
    once. A pair with inlier matches must refer to two images of the database: COLMAP's
    own mapper fails on one that does not (``DatabaseCache``), so it is refused here too.

    Returns:
        How many pairs with inlier matches were left out, by reason: ``"degenerate"``
        (DEGENERATE or WATERMARK configuration) and ``"duplicate"`` (the matched
        keypoints coincide, see ``DUPLICATE_DISPLACEMENT_PX``).
    """
    skipped: Counter[str] = Counter()
    pairs: list[Pair] = []
    displacements: list[np.ndarray] = []
    spacing = np.linspace(0.0, 1.0, DUPLICATE_SAMPLE)
    ids, largest = np.asarray(pair_ids, dtype=np.uint64), np.uint64(MAX_NUM_IMAGES)
    image_pairs = np.column_stack([ids // largest, ids % largest]).tolist()
    for pair_id, (id1, id2), tvg in zip(pair_ids, image_pairs, geometries, strict=True):
        inliers = np.asarray(tvg.inlier_matches).reshape(-1, 2)
        if inliers.shape[0] < 1:
            continue
        _check_pair_images(pair_id, (id1, id2), contents, path)
        if int(tvg.config) in _EXCLUDED_CONFIGS:
            skipped["degenerate"] += 1
            continue
        fundamental = _pair_fundamental(tvg, contents, id1, id2) if fundamentals else None
        if id1 > id2:  # COLMAP normalises pairs to id1 < id2; kept for safety
            id1, id2 = id2, id1
            inliers = inliers[:, ::-1]
            fundamental = None if fundamental is None else fundamental.T
        keypoints1, keypoints2 = contents.keypoints[id1], contents.keypoints[id2]
        inliers = inliers.astype(np.int32)
        if np.any(inliers < 0) or np.any(inliers.max(axis=0) >= (len(keypoints1), len(keypoints2))):
            raise CalibrationError(
                f"corrupt database: match indices out of range for images {id1} and {id2}: {path}"
            )
        sample = inliers[(spacing * (len(inliers) - 1)).astype(np.int64)]
        displacements.append(keypoints1[sample[:, 0]] - keypoints2[sample[:, 1]])
        pairs.append((id1, id2))
        contents.matches[(id1, id2)] = inliers
        if fundamental is not None:
            contents.fundamentals[(id1, id2)] = fundamental
    if pairs:
        skipped["duplicate"] += _drop_duplicates(pairs, displacements, contents)
    if skipped["degenerate"]:
        logger.info("ignored %d degenerate or watermark image pairs", skipped["degenerate"])
    return skipped


def _check_pair_images(
    pair_id: int, image_ids: tuple[int, int], contents: DatabaseContents, path: Path
) -> None:
    """CalibrationError unless both images of a verified pair are in the database."""
    unknown = [i for i in image_ids if i not in contents.image_names]
    if unknown:
        raise CalibrationError(
            f"corrupt database: verified image pair {pair_id} refers to image id "
            f"{unknown[0]}, which the database does not have: {path}"
        )


def _drop_duplicates(
    pairs: list[Pair], displacements: list[np.ndarray], contents: DatabaseContents
) -> int:
    """Remove, in place, the pairs whose sampled matches barely move (median displacement
    below ``DUPLICATE_DISPLACEMENT_PX``: the same image twice); how many."""
    median = np.median(np.linalg.norm(np.stack(displacements), axis=-1), axis=1)
    duplicates = np.array(pairs)[median < DUPLICATE_DISPLACEMENT_PX]
    for id1, id2 in duplicates:
        logger.info("images %d and %d look identical (no baseline); pair ignored", id1, id2)
        del contents.matches[(int(id1), int(id2))]
        contents.fundamentals.pop((int(id1), int(id2)), None)
    return len(duplicates)


def _rig_sensor_cameras(rigs: list[pycolmap.Rig]) -> set[int]:
    """Camera ids that share a rig with another camera sensor."""
    cameras: set[int] = set()
    for rig in rigs:
        ids = {int(s.id) for s in rig.sensor_ids() if s.type == pycolmap.SensorType.CAMERA}
        if len(ids) > 1:
            cameras |= ids
    return cameras


#: Blobs pycolmap reads with the shape stored next to them: (table, bytes per value).
_SHAPED_BLOBS = (("keypoints", 4), ("two_view_geometries", 4))


def _check_snapshot(snapshot: Path, path: Path) -> int:
    """Refuse blobs pycolmap would misread; return the number of pairs with raw matches.

    pycolmap trusts the shape stored next to a blob: a negative or too large ``rows``
    makes it allocate without bound (``std::bad_alloc``), a short blob is read past its
    end, and a blob of another column count than COLMAP writes is not (x, y, ...) or
    (index1, index2).
    """
    con = connect(snapshot, "mode=ro")
    try:
        for table, itemsize in _SHAPED_BLOBS:
            row = con.execute(
                f"SELECT rowid, rows, cols FROM {table} WHERE rows < 0 OR cols < 0 OR "
                f"(rows > 0 AND cols > 0 AND length(data) IS NOT rows * cols * {itemsize}) "
                "LIMIT 1"
            ).fetchone()
            if row is not None:
                raise CalibrationError(
                    f"corrupt database: {table} row {row[0]} claims {row[1]}x{row[2]} values "
                    f"that its data does not hold: {path}"
                )
        columns = ", ".join(map(str, KEYPOINT_COLUMNS))
        row = con.execute(
            "SELECT keypoints.image_id, images.name, keypoints.cols FROM keypoints "
            f"LEFT JOIN images USING (image_id) WHERE rows > 0 AND cols NOT IN ({columns}) "
            "LIMIT 1"
        ).fetchone()
        if row is not None:
            raise CalibrationError(
                f"corrupt database: the keypoints of image {row[0]} ({row[1]}) have "
                f"{_columns(row[2])}, COLMAP writes 2, 4 or 6: {path}"
            )
        row = con.execute(
            "SELECT pair_id, cols FROM two_view_geometries WHERE rows > 0 AND cols != 2 LIMIT 1"
        ).fetchone()
        if row is not None:
            raise CalibrationError(
                f"corrupt database: the inlier matches of image pair {row[0]} have "
                f"{_columns(row[1])}, COLMAP writes 2: {path}"
            )
        tables = {name for (name,) in con.execute("SELECT name FROM sqlite_master")}
        if "matches" not in tables:
            return 0
        return int(con.execute("SELECT COUNT(*) FROM matches WHERE rows > 0").fetchone()[0])
    except sqlite3.Error as exc:
        raise database_error(exc, path) from exc
    finally:
        con.close()


def _columns(count: int) -> str:
    return f"{count} column" if count == 1 else f"{count} columns"


def _check_keypoints_finite(contents: DatabaseContents, path: Path) -> None:
    """Refuse NaN or infinite keypoint coordinates (they poison every tensor they touch)."""
    for image_id, xy in contents.keypoints.items():
        if not np.all(np.isfinite(xy)):
            bad = int(np.count_nonzero(~np.all(np.isfinite(xy), axis=1)))
            raise CalibrationError(
                f"corrupt database: {bad} keypoint(s) of image {image_id} "
                f"({contents.image_names[image_id]}) are NaN or infinite: {path}"
            )


def _read_snapshot(
    snapshot: Path, path: Path, *, fundamentals: bool = False
) -> tuple[DatabaseContents, Counter[str]]:
    """Read the snapshot (checked by :func:`_check_snapshot`) with pycolmap (``path`` is only
    used in messages).

    Returns:
        The contents and the pairs left out by reason (see :func:`_verified_pairs`).
    """
    contents = DatabaseContents()
    try:
        with pycolmap.Database.open(str(snapshot)) as db:
            for cam in db.read_all_cameras():
                contents.cameras[int(cam.camera_id)] = CameraInfo.from_pycolmap(cam)
            for image in db.read_all_images():
                image_id = int(image.image_id)
                contents.image_names[image_id] = image.name
                contents.image_camera[image_id] = int(image.camera_id)
                contents.keypoints[image_id] = _keypoints_xy(db.read_keypoints(image_id))
            pair_ids, geometries = db.read_two_view_geometries()
            contents.rig_sensor_cameras = _rig_sensor_cameras(db.read_all_rigs())
    except (RuntimeError, ValueError, MemoryError) as exc:  # pycolmap's errors
        raise database_error(exc, path) from exc
    _check_keypoints_finite(contents, path)
    missing = sorted(set(contents.image_camera.values()) - set(contents.cameras))
    if missing:
        raise CalibrationError(
            f"corrupt database: images refer to missing camera {missing[0]}: {path}"
        )
    skipped = _verified_pairs(pair_ids, geometries, contents, path, fundamentals=fundamentals)
    return contents, skipped


def _no_matches_error(skipped: Counter[str], num_matched_pairs: int, path: Path) -> str:
    """Why there is nothing to calibrate from, for a database with images but no usable pair."""
    if skipped:
        reasons = []
        if skipped["degenerate"]:
            reasons.append(f"{skipped['degenerate']} are DEGENERATE or WATERMARK")
        if skipped["duplicate"]:
            reasons.append(
                f"{skipped['duplicate']} are duplicates (the matched keypoints coincide: "
                "the same image twice, no baseline)"
            )
        total = sum(skipped.values())
        return (
            f"database has no usable verified matches: of {total} verified image pairs "
            f"{' and '.join(reasons)}: {path}"
        )
    if num_matched_pairs:
        return (
            f"database has no verified matches ({num_matched_pairs} image pairs have raw "
            f"matches; run COLMAP's geometric verification): {path}"
        )
    return f"database has no verified matches (run COLMAP feature matching first): {path}"


def read_database(path: Path, *, fundamentals: bool = False) -> DatabaseContents:
    """Read cameras, images, raw keypoints and verified matches from a COLMAP database.

    The file at ``path`` stays byte-identical and no companion files are left behind
    (see :func:`.sqlite_files.copy_database`). Pairs flagged DEGENERATE or WATERMARK, and
    pairs of identical images (see ``DUPLICATE_DISPLACEMENT_PX``), are ignored.

    Args:
        path: the COLMAP database.
        fundamentals: also fill ``DatabaseContents.fundamentals`` (the stored F, or F
            from a stored E); the calibration does not need them.

    Raises:
        CalibrationError: the path is missing, a directory, not an SQLite/COLMAP database,
            locked or corrupt; or it has fewer than 3 images, no keypoints or no usable
            verified matches.
    """
    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="colmap_trifocal_") as tmp:
        snapshot = Path(tmp) / "snapshot.db"
        copy_database(path, snapshot, without_blobs=SKIPPED_TABLES, temporary=True)
        num_matched_pairs = _check_snapshot(snapshot, path)
        contents, skipped = _read_snapshot(snapshot, path, fundamentals=fundamentals)
    num_images = len(contents.image_names)
    if num_images == 0:
        raise CalibrationError(f"database has no images: {path}")
    if num_images < MIN_IMAGES:
        noun = "image" if num_images == 1 else "images"
        raise CalibrationError(
            f"database has only {num_images} {noun}, at least {MIN_IMAGES} are needed: {path}"
        )
    if not any(len(xy) for xy in contents.keypoints.values()):
        raise CalibrationError(
            f"database has no keypoints (run COLMAP feature extraction first): {path}"
        )
    if not contents.matches:
        raise CalibrationError(_no_matches_error(skipped, num_matched_pairs, path))
    logger.info(
        "read %s: %d cameras, %d images, %d verified pairs (%d with F)",
        path,
        len(contents.cameras),
        num_images,
        len(contents.matches),
        len(contents.fundamentals),
    )
    return contents
