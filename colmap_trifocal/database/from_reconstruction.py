"""A COLMAP reconstruction as the calibration's input: its 2D–3D tracks as verified matches.

``calibrate_reconstruction`` calibrates from a model (``sparse/0``, or a
``pycolmap.Reconstruction`` in memory) instead of a database. What the calibration
needs is what :func:`.snapshot.read_database` gives (:class:`.snapshot.DatabaseContents`):

* cameras: the model's cameras of registered images, params as the model holds them
  (bundle-adjusted; the distortion is what undistorts the keypoints);
* images: the registered images (an unregistered image has no track);
* keypoints: every ``points2D`` of an image, in its order, so that a track element's
  ``point2D_idx`` indexes them (pixels, COLMAP's convention: the centre of the top-left
  pixel at (0.5, 0.5));
* matches: two observations of one 3D point in two images are a match of that pair
  (a track of n images gives n(n−1)/2 matches). A track that sees an image twice keeps
  its first observation there.

The 3D points and poses themselves are not used: the calibration sees only which
keypoints the model tied together, as it sees a database's verified matches.

Grouping: bundle adjustment refines each camera id on its own, so the copies of one
physical camera that COLMAP's feature extraction makes (one camera per image, equal
params) leave a reconstruction with slightly different params each.
:func:`grouping_cameras` gives the cameras ``auto`` compares for a model: ids with the
same model, size and prior flag whose focal lengths lie within
:data:`MODEL_FOCAL_TOLERANCE` of each other count as one camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..common.log import logger
from .cameras import CameraInfo
from .model_files import check_binary_model, check_regular_files
from .snapshot import MIN_IMAGES, DatabaseContents

#: Files a COLMAP model folder has, each as ``.bin`` or ``.txt``.
MODEL_FILES = ("cameras", "images", "points3D")

#: Camera ids of a model whose model, image size and prior flag agree are one physical
#: camera under ``auto`` when their focal lengths lie within this fraction of the smallest
#: focal length of the cluster (per-image bundle adjustment scatters one camera's focal
#: length by well under this; two lenses of one sensor size differ by more).
MODEL_FOCAL_TOLERANCE = 0.05

#: pycolmap's point3D_id of a keypoint that observes no 3D point.
_NO_POINT3D = np.iinfo(np.uint64).max


def read_reconstruction(path: Path | str) -> pycolmap.Reconstruction:
    """Read a COLMAP model folder (``.bin`` or ``.txt`` files, e.g. ``sparse/0``).

    Binary files are checked against their header counts first (pycolmap trusts them and
    allocates without bound on a truncated file, see :mod:`.model_files`).

    Raises:
        CalibrationError: the folder is missing, lacks cameras/images/points3D files, or
            they cannot be parsed.
    """
    path = Path(path)
    if not path.is_dir():
        raise CalibrationError(f"model folder not found: {path}")
    check_regular_files(path)
    missing = [
        name
        for name in MODEL_FILES
        if not any((path / f"{name}{ext}").is_file() for ext in (".bin", ".txt"))
    ]
    if missing:
        raise CalibrationError(f"not a COLMAP model (no {', '.join(missing)} .bin/.txt) in {path}")
    check_binary_model(path)
    try:
        return pycolmap.Reconstruction(str(path))
    except (ValueError, RuntimeError, MemoryError, OSError, IndexError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationError(f"cannot read the COLMAP model in {path}: {reason}") from exc


def _observations(
    reconstruction: pycolmap.Reconstruction, image_ids: list[int]
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """Keypoints of each image and every observation of a 3D point.

    Returns:
        image_id -> (n, 2) float64 pixel coordinates of its ``points2D``; and an (k, 3)
        uint64 array of observations ``(point3D_id, image_id, point2D_idx)``.
    """
    keypoints: dict[int, np.ndarray] = {}
    observed = []
    for image_id in image_ids:
        points = reconstruction.image(image_id).points2D
        xy = np.array([p.xy for p in points], dtype=np.float64).reshape(-1, 2)
        point3d = np.array([p.point3D_id for p in points], dtype=np.uint64)
        keypoints[image_id] = xy
        index = np.flatnonzero(point3d != _NO_POINT3D)
        observed.append(
            np.stack([point3d[index], np.full(len(index), image_id, np.uint64), index], axis=1)
        )
    rows = np.concatenate(observed).astype(np.uint64) if observed else np.zeros((0, 3), np.uint64)
    return keypoints, rows


def track_matches(observations: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """Pairwise matches of the tracks: two observations of one 3D point in two images.

    Args:
        observations: (k, 3) integer rows ``(point3D_id, image_id, point2D_idx)``.

    Returns:
        (id1, id2), id1 < id2 -> (m, 2) int32 keypoint indices (column 0 in image id1,
        column 1 in id2), ordered by 3D point id. A track that observes an image twice
        keeps the observation with the smaller keypoint index.
    """
    rows = np.asarray(observations, dtype=np.int64).reshape(-1, 3)
    if len(rows) == 0:
        return {}
    rows = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))]
    rows = rows[np.r_[True, np.any(rows[1:, :2] != rows[:-1, :2], axis=1)]]
    starts = np.flatnonzero(np.r_[True, rows[1:, 0] != rows[:-1, 0]])
    lengths = np.diff(np.r_[starts, len(rows)])
    firsts, seconds = [], []
    for length in np.unique(lengths[lengths >= 2]):  # one pass per track length
        members = starts[lengths == length][:, None] + np.arange(length)
        a, b = np.triu_indices(int(length), 1)
        firsts.append(members[:, a].ravel())
        seconds.append(members[:, b].ravel())
    if not firsts:
        return {}
    first, second = np.concatenate(firsts), np.concatenate(seconds)
    image1, image2 = rows[first, 1], rows[second, 1]  # image1 < image2: sorted in a track
    order = np.lexsort((rows[first, 0], image2, image1))
    image1, image2, first, second = image1[order], image2[order], first[order], second[order]
    breaks = np.flatnonzero((np.diff(image1) != 0) | (np.diff(image2) != 0)) + 1
    pairs = np.stack([rows[first, 2], rows[second, 2]], axis=1).astype(np.int32)
    return {
        (int(image1[chunk[0]]), int(image2[chunk[0]])): np.ascontiguousarray(pairs[chunk])
        for chunk in np.split(np.arange(len(first)), breaks)
    }


def _rig_sensor_cameras(reconstruction: pycolmap.Reconstruction) -> set[int]:
    """Camera ids that share a rig with another camera sensor."""
    cameras: set[int] = set()
    for rig in reconstruction.rigs.values():
        ids = {int(s.id) for s in rig.sensor_ids() if s.type == pycolmap.SensorType.CAMERA}
        if len(ids) > 1:
            cameras |= ids
    return cameras


def contents_from_reconstruction(reconstruction: pycolmap.Reconstruction) -> DatabaseContents:
    """The calibration's input from a reconstruction's tracks (see the module docstring).

    Raises:
        CalibrationError: fewer than 3 registered images, non-finite keypoints, or no 3D
            point seen in two of them.
    """
    image_ids = sorted(int(i) for i in reconstruction.reg_image_ids())
    if len(image_ids) < MIN_IMAGES:
        raise CalibrationError(
            f"the reconstruction has {len(image_ids)} registered image(s), at least "
            f"{MIN_IMAGES} are needed"
        )
    contents = DatabaseContents()
    for image_id in image_ids:
        image = reconstruction.image(image_id)
        camera_id = int(image.camera_id)
        contents.image_names[image_id] = image.name
        contents.image_camera[image_id] = camera_id
        if camera_id not in contents.cameras:
            contents.cameras[camera_id] = CameraInfo.from_pycolmap(reconstruction.camera(camera_id))
    contents.keypoints, observations = _observations(reconstruction, image_ids)
    for image_id, xy in contents.keypoints.items():
        if not np.all(np.isfinite(xy)):
            raise CalibrationError(
                f"the reconstruction's image {image_id} ({contents.image_names[image_id]}) "
                "has NaN or infinite keypoint coordinates"
            )
    contents.matches = track_matches(observations)
    contents.rig_sensor_cameras = _rig_sensor_cameras(reconstruction)
    if not contents.matches:
        raise CalibrationError("the reconstruction has no 3D point seen in two images")
    logger.info(
        "read a reconstruction: %d cameras, %d registered images, %d image pairs from %d tracks",
        len(contents.cameras),
        len(image_ids),
        len(contents.matches),
        len(np.unique(observations[:, 0])),
    )
    return contents


def grouping_cameras(cameras: dict[int, CameraInfo]) -> dict[int, CameraInfo]:
    """The cameras ``auto`` grouping compares for a reconstruction (not for calibrating).

    Camera ids with the same model, size and prior flag are sorted by focal length
    (the mean of fx and fy, pixels); a run of them within :data:`MODEL_FOCAL_TOLERANCE`
    of the run's first focal length gets that first camera's params, so that
    :func:`.camera_groups.group_cameras` with ``auto`` puts them in one group.

    Args:
        cameras: camera_id -> camera as the reconstruction holds it.

    Returns:
        camera_id -> a copy whose params are its cluster's representative ones.
    """
    classes: dict[tuple, list[CameraInfo]] = {}
    for camera in cameras.values():
        key = (camera.model, camera.width, camera.height, camera.has_prior_focal_length)
        classes.setdefault(key, []).append(camera)
    grouped: dict[int, CameraInfo] = {}
    for members in classes.values():
        focal = np.array([np.mean(c.intrinsics[:2]) for c in members])
        order = np.argsort(focal, kind="stable")
        representative = members[order[0]]
        for k in order:
            camera = members[k]
            base = np.mean(representative.intrinsics[:2])
            if not focal[k] <= base * (1.0 + MODEL_FOCAL_TOLERANCE):
                representative = camera
            grouped[camera.camera_id] = CameraInfo(
                camera.camera_id,
                camera.model,
                camera.width,
                camera.height,
                representative.params,
                camera.has_prior_focal_length,
            )
    return grouped


def model_intrinsics(cameras: list[CameraInfo]) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a group's cameras as the model holds them: their mean (pixels)."""
    values = np.mean([c.intrinsics for c in cameras], axis=0)
    return (float(values[0]), float(values[1]), float(values[2]), float(values[3]))
