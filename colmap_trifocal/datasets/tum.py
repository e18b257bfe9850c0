"""TUM RGB-D sequences (Sturm et al., IROS 2012), colour images only.

Kind ``tum``; ``path`` is a sequence folder (e.g. ``rgbd_dataset_freiburg1_xyz``)
holding ``rgb.txt`` (``timestamp filename`` lines, ``#`` comments), the ``rgb/``
images and optionally ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, the
camera-to-world pose of the colour camera).

Intrinsics: ``intrinsics.txt`` in the folder (one line ``fx fy cx cy``, OpenCV
convention) if present, else the published table for the ``freiburgN`` in the
folder name (fr1, fr2, fr3; 640x480). fr1 and fr2 images are distorted (the
published distortion is not applied here); fr3 images are undistorted. TUM uses
the OpenCV pixel convention: cx, cy + 0.5.

Poses: the ground-truth line nearest in time to each image, if within
``max_time_difference`` (0.02 s); other views get no pose.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..common.errors import CalibrationError
from .base import (
    OPENCV_TO_COLMAP,
    DatasetScene,
    GroundTruthView,
    image_size,
    number_rows,
    parsing,
    pose_from_camera_to_world,
    require_dir,
    require_file,
    text_rows,
)

#: Published (fx, fy, cx, cy) of the colour cameras, OpenCV convention, 640x480.
PUBLISHED_INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}
PUBLISHED_SIZE = (640, 480)
_FREIBURG = re.compile(r"(?:freiburg|(?<![a-z])fr)([123])", re.IGNORECASE)


def read_tum_scene(path: Path | str, max_time_difference: float = 0.02) -> DatasetScene:
    """A TUM RGB-D sequence folder as a :class:`DatasetScene` (rgb.txt order)."""
    sequence = require_dir(path, "TUM sequence folder")
    rgb_file = require_file(sequence / "rgb.txt", "TUM image list")
    with parsing(rgb_file, "TUM image list"):
        rows = text_rows(rgb_file)
        times = np.array([r[0] for r in rows], dtype=float)
        names = [r[1] for r in rows]
    if not names:
        raise CalibrationError(f"no images listed in {rgb_file}")
    intrinsics, size = _intrinsics(sequence, names[0])

    extrinsics: list[np.ndarray | None] = [None] * len(names)
    gt_file = sequence / "groundtruth.txt"
    if gt_file.is_file():
        gt_times, poses = read_groundtruth(gt_file)
        nearest = _nearest(gt_times, times)
        matched = np.abs(gt_times[nearest] - times) <= max_time_difference
        pairs = zip(poses[nearest], matched, strict=True)
        extrinsics = [pose if ok else None for pose, ok in pairs]

    views = [
        GroundTruthView(
            name=name,
            intrinsics=intrinsics,
            width=size[0],
            height=size[1],
            rotation=None if pose is None else pose[:, :3],
            translation=None if pose is None else pose[:, 3],
        )
        for name, pose in zip(names, extrinsics, strict=True)
    ]
    return DatasetScene(kind="tum", name=sequence.name, image_dir=sequence, views=views)


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Sorted timestamps (N,) and world-to-camera [R | t] (N, 3, 4) of a ``groundtruth.txt``."""
    with parsing(path, "TUM ground truth"):
        rows = np.array(number_rows(path), dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 8 or len(rows) == 0:
            raise ValueError("expected lines of 8 numbers: timestamp tx ty tz qx qy qz qw")
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    rotations = rotations_from_quaternions(rows[:, 4:8])
    return rows[:, 0], pose_from_camera_to_world(rotations, rows[:, 1:4])


def rotations_from_quaternions(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices from (N, 4) quaternions ``qx qy qz qw`` (normalised here)."""
    x, y, z, w = (np.asarray(q, dtype=float) / np.linalg.norm(q, axis=-1, keepdims=True)).T
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)


def _nearest(sorted_times: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of ``sorted_times`` for each of ``times``."""
    if len(sorted_times) == 1:
        return np.zeros(len(times), dtype=int)
    after = np.clip(np.searchsorted(sorted_times, times), 1, len(sorted_times) - 1)
    before = after - 1
    closer_before = np.abs(times - sorted_times[before]) <= np.abs(sorted_times[after] - times)
    return np.where(closer_before, before, after)


def _intrinsics(sequence: Path, first_image: str) -> tuple[np.ndarray, tuple[int | None, ...]]:
    """(fx, fy, cx, cy) in COLMAP's convention and (width, height)."""
    size = image_size(sequence / first_image)
    custom = sequence / "intrinsics.txt"
    if custom.is_file():
        with parsing(custom, "TUM intrinsics file"):
            values = np.array(number_rows(custom), dtype=float).reshape(4)
        return values + OPENCV_TO_COLMAP, size or (None, None)
    match = _FREIBURG.search(sequence.resolve().name)
    if match is None:
        raise CalibrationError(
            f"no intrinsics.txt in {sequence} and no freiburg1/2/3 in its name: "
            "cannot tell the TUM camera"
        )
    published = np.array(PUBLISHED_INTRINSICS[int(match.group(1))])
    return published + OPENCV_TO_COLMAP, size or PUBLISHED_SIZE
