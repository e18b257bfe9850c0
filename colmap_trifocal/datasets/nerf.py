"""NeRF's synthetic scenes (Mildenhall et al., ECCV 2020: lego, chair, …).

Kind ``nerf``; ``path`` is a folder holding a ``transforms_*.json`` (option ``split``:
``train`` by default, or a file name) with ``camera_angle_x`` (the horizontal field of
view, radians) and ``frames``: each a ``file_path`` relative to the folder (``.png``
added where it has no suffix) and a 4x4 camera-to-world ``transform_matrix`` in
OpenGL's axes (x right, y up, z backwards). The renders are pinhole with square pixels
and the principal point at the image centre: ``fx = fy = (W / 2) / tan(angle / 2)``,
``cx = W / 2``, ``cy = H / 2`` in COLMAP's pixel convention (no shift: the renders'
rays go through pixel centres at ``i + 0.5``). Poses become world-to-camera in
OpenCV's axes (y down, z forward). Width and height come from the first image.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..common.errors import CalibrationError
from .base import (
    DatasetScene,
    GroundTruthView,
    image_size,
    parsing,
    pose_from_camera_to_world,
    require_dir,
    require_file,
)

#: OpenGL camera axes to OpenCV's: y and z flip.
GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def read_nerf_scene(path: Path | str, split: str = "train") -> DatasetScene:
    """A NeRF synthetic folder as a :class:`DatasetScene` (one view per frame)."""
    folder = require_dir(path, "NeRF folder")
    name = split if split.endswith(".json") else f"transforms_{split}.json"
    transforms = require_file(folder / name, "NeRF transforms file")
    with parsing(transforms, "NeRF transforms file"):
        data = json.loads(transforms.read_text())
        angle = float(data["camera_angle_x"])
        frames = data["frames"]
        if not isinstance(frames, list) or not frames:
            raise ValueError("no frames")
        names = [_image_name(str(f["file_path"])) for f in frames]
        c2w = np.array([f["transform_matrix"] for f in frames], dtype=float)
        if c2w.shape != (len(frames), 4, 4) or not 0.0 < angle < math.pi:
            raise ValueError("expected 4x4 transform matrices and 0 < camera_angle_x < pi")
    size = image_size(folder / names[0])
    if size is None:
        raise CalibrationError(f"cannot read the NeRF image {folder / names[0]}")
    width, height = size
    focal = 0.5 * width / math.tan(0.5 * angle)
    intrinsics = np.array([focal, focal, 0.5 * width, 0.5 * height])
    poses = pose_from_camera_to_world(c2w[:, :3, :3] @ GL_TO_CV, c2w[:, :3, 3])
    views = [
        GroundTruthView(n, intrinsics, width, height, pose[:, :3], pose[:, 3])
        for n, pose in zip(names, poses, strict=True)
    ]
    return DatasetScene(kind="nerf", name=folder.name, image_dir=folder, views=views)


def _image_name(file_path: str) -> str:
    """A frame's ``file_path`` as an image name relative to the folder."""
    name = file_path.removeprefix("./")
    return name if Path(name).suffix else f"{name}.png"
