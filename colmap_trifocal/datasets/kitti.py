"""KITTI odometry sequences (Geiger et al., CVPR 2012).

Kind ``kitti``; ``path`` is a sequence folder ``<root>/sequences/XX`` holding
``calib.txt`` (lines ``P0: 12 numbers`` ... ``P3:``, ``Tr:``) and the rectified
image folders ``image_0`` ... ``image_3``. Options:

* ``camera``: which camera (default 2 if ``image_2`` exists, else 0);
* ``poses``: a KITTI poses file (one 3x4 camera-0-to-world matrix per line, one
  line per frame); default ``<root>/poses/XX.txt`` if it exists, else no poses.

K is ``P_camera[:, :3]`` (rectified, shared by all frames). Camera c sits at the
baseline ``b_c = K⁻¹ P_c[:, 3]`` from camera 0 with the same rotation, so its
world-to-camera pose is ``R = R_0``, ``t = t_0 + b_c`` where ``R_0 = Rᵀ_pose``,
``t_0 = −R_0 C_0``. KITTI uses the OpenCV pixel convention: cx, cy + 0.5.
Width and height come from the first image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common.errors import CalibrationError
from .base import (
    DatasetScene,
    GroundTruthView,
    from_opencv,
    image_size,
    list_images,
    number_rows,
    parsing,
    pose_from_camera_to_world,
    require_dir,
    require_file,
    text_rows,
)


def read_kitti_scene(
    path: Path | str, camera: int | None = None, poses: Path | str | None = None
) -> DatasetScene:
    """A KITTI odometry sequence folder as a :class:`DatasetScene` (one view per frame)."""
    sequence = require_dir(path, "KITTI sequence folder")
    if camera is None:
        camera = 2 if (sequence / "image_2").is_dir() else 0
    if camera not in (0, 1, 2, 3):
        raise CalibrationError(f"KITTI camera must be 0, 1, 2 or 3, not {camera}")
    matrices = read_calib_file(sequence / "calib.txt")
    if f"P{camera}" not in matrices:
        calib = sequence / "calib.txt"
        raise CalibrationError(f"cannot read KITTI calibration file {calib}: no P{camera} line")
    projection = matrices[f"P{camera}"]
    image_dir = sequence / f"image_{camera}"
    names = list_images(image_dir)
    if not names:
        raise CalibrationError(f"no images in {image_dir}")
    K = projection[:, :3]
    intrinsics = from_opencv(K)
    width, height = image_size(image_dir / names[0]) or (None, None)

    poses_file = Path(poses) if poses is not None else _default_poses_file(sequence)
    extrinsics: list[np.ndarray | None] = [None] * len(names)
    if poses_file is not None:
        camera0_to_world = read_poses_file(poses_file)
        if len(camera0_to_world) != len(names):
            raise CalibrationError(
                f"{poses_file} has {len(camera0_to_world)} poses for {len(names)} images"
            )
        world_to_camera = pose_from_camera_to_world(
            camera0_to_world[:, :, :3], camera0_to_world[:, :, 3]
        )
        world_to_camera[:, :, 3] += np.linalg.solve(K, projection[:, 3])
        extrinsics = list(world_to_camera)

    views = [
        GroundTruthView(
            name=name,
            intrinsics=intrinsics,
            width=width,
            height=height,
            rotation=None if pose is None else pose[:, :3],
            translation=None if pose is None else pose[:, 3],
        )
        for name, pose in zip(names, extrinsics, strict=True)
    ]
    return DatasetScene(kind="kitti", name=sequence.name, image_dir=image_dir, views=views)


def read_calib_file(path: Path) -> dict[str, np.ndarray]:
    """Key (``P0`` ... ``P3``, ``Tr``) -> 3x4 matrix of a KITTI ``calib.txt``.

    Only the lines present are returned (a grayscale-only sequence has just P0 and P1).
    """
    require_file(path, "KITTI calibration file")
    with parsing(path, "KITTI calibration file"):
        matrices = {
            row[0].rstrip(":"): np.array(row[1:], dtype=float).reshape(3, 4)
            for row in text_rows(path)
        }
        if not any(key.startswith("P") for key in matrices):
            raise ValueError("no projection matrix (P0 ... P3)")
    return matrices


def read_poses_file(path: Path) -> np.ndarray:
    """(N, 3, 4) camera-0-to-world matrices of a KITTI poses file."""
    require_file(path, "KITTI poses file")
    with parsing(path, "KITTI poses file"):
        rows = np.array(number_rows(path), dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 12:
            raise ValueError("expected 12 numbers per line")
    return rows.reshape(-1, 3, 4)


def _default_poses_file(sequence: Path) -> Path | None:
    candidate = sequence.resolve().parent.parent / "poses" / f"{sequence.resolve().name}.txt"
    return candidate if candidate.is_file() else None
