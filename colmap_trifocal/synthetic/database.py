"""Synthetic scenes as COLMAP database contents, and as database files.

``scene_contents`` gives what :func:`.database.read_database` would return for a
database of the scene, without writing one (fast, for experiments);
``write_database`` writes a real COLMAP database with pycolmap (for the command
line and tests that read files).

Conventions: one PINHOLE camera (id 1, params the scene's true intrinsics; a
prior is passed to the calibration separately), one image per view (ids
``1..m``, names ``0001.png``, ...), keypoints = the view's observations in
pixels with COLMAP's convention (track ``k`` is keypoint ``k`` in every image),
and for every pair of images the tracks visible in both as verified matches
(outlier tracks included, as a matcher could not tell them apart). No
fundamental matrices: the ``fundamental`` method re-fits F from the matches.
"""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np
import pycolmap

from ..database.cameras import CameraInfo
from ..database.snapshot import DatabaseContents
from .scenes import SyntheticScene

CAMERA_ID = 1


def scene_contents(scene: SyntheticScene) -> DatabaseContents:
    """The scene as the contents of a COLMAP database (see the module conventions)."""
    camera = CameraInfo(CAMERA_ID, "PINHOLE", scene.width, scene.height, scene.intrinsics)
    image_ids = range(1, scene.num_cameras + 1)
    visible = (
        np.ones((scene.num_cameras, scene.num_points), dtype=bool)
        if scene.visible is None
        else scene.visible
    )
    matches = {}
    for i, j in combinations(image_ids, 2):
        common = np.flatnonzero(visible[i - 1] & visible[j - 1]).astype(np.int64)
        if len(common):
            matches[(i, j)] = np.ascontiguousarray(np.stack([common, common], axis=1))
    return DatabaseContents(
        cameras={CAMERA_ID: camera},
        image_names={i: f"{i:04d}.png" for i in image_ids},
        image_camera={i: CAMERA_ID for i in image_ids},
        keypoints={i: np.array(scene.observations[i - 1], dtype=np.float64) for i in image_ids},
        matches=matches,
    )


def write_database(
    contents: DatabaseContents, path: Path, intrinsics: np.ndarray | None = None
) -> Path:
    """Write contents to a new COLMAP database at ``path`` (pycolmap).

    Every camera gets a trivial rig and every image a frame, as COLMAP's feature
    extraction makes them; verified matches are stored as UNCALIBRATED two-view
    geometries (and as raw matches).

    Args:
        contents: cameras, images, keypoints and matches to store.
        path: the new database (must not exist).
        intrinsics: (fx, fy, cx, cy) stored for every PINHOLE camera instead of its
            params, e.g. a wrong starting camera (pixels).
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(path)
    with pycolmap.Database.open(str(path)) as db:
        for camera_id, info in contents.cameras.items():
            params = info.params if intrinsics is None else np.asarray(intrinsics, float)
            camera = pycolmap.Camera.create_from_model_name(
                camera_id, info.model, 1.0, info.width, info.height
            )
            camera.params = np.asarray(params, float).tolist()
            db.write_camera(camera, use_camera_id=True)
            rig = pycolmap.Rig(rig_id=camera_id)
            rig.add_ref_sensor(camera.sensor_id)
            db.write_rig(rig, use_rig_id=True)
        for image_id, name in contents.image_names.items():
            camera_id = contents.image_camera[image_id]
            image = pycolmap.Image(name=name, camera_id=camera_id, image_id=image_id)
            db.write_image(image, use_image_id=True)
            frame = pycolmap.Frame(frame_id=image_id, rig_id=camera_id)
            frame.add_data_id(image.data_id)
            db.write_frame(frame, use_frame_id=True)
            db.write_keypoints(image_id, contents.keypoints[image_id].astype(np.float32))
        for (id1, id2), matches in contents.matches.items():
            pairs = matches.astype(np.uint32)
            db.write_matches(id1, id2, pairs)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            geometry.inlier_matches = pairs
            db.write_two_view_geometry(id1, id2, geometry)
    return path


def wrong_partners(
    matches: np.ndarray, ratio: float, num_keypoints: int, rng: np.random.Generator
) -> np.ndarray:
    """A copy of matches (m, 2) with a share ``ratio`` given a random wrong partner.

    Each chosen match keeps its keypoint in the first image and gets another
    keypoint (never the true one) of the second image, which has
    ``num_keypoints``: a wrong match that geometric verification let through.
    """
    result = np.array(matches, dtype=np.int64).reshape(-1, 2)
    wrong = rng.random(len(result)) < ratio
    offsets = rng.integers(1, max(num_keypoints, 2), size=int(wrong.sum()))
    result[wrong, 1] = (result[wrong, 1] + offsets) % num_keypoints
    return result


def corrupt_verified_matches(db: pycolmap.Database, ratio: float, rng: np.random.Generator) -> None:
    """Give a share ``ratio`` of every pair's verified matches a wrong partner (in place).

    pycolmap's ``SyntheticDatasetOptions.inlier_match_ratio`` only adds wrong matches
    to the raw ``matches`` table; the verified two-view geometries, which the
    calibration reads, stay clean. This puts them where they matter. The raw matches
    are set to the verified ones.
    """
    if ratio <= 0.0:
        return
    pair_ids, geometries = db.read_two_view_geometries()
    for pair_id, geometry in zip(pair_ids, geometries, strict=True):
        id1, id2 = (int(i) for i in pycolmap.pair_id_to_image_pair(pair_id))
        size = db.num_keypoints_for_image(id2)
        matches = wrong_partners(geometry.inlier_matches, ratio, size, rng).astype(np.uint32)
        geometry.inlier_matches = matches
        db.update_two_view_geometry(id1, id2, geometry)
        db.delete_matches(id1, id2)
        db.write_matches(id1, id2, matches)
