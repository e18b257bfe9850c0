"""Strecha et al. (CVPR 2008) scenes as published by openMVG (fountain-P11, Herz-Jesus-P8, ...).

Layout per scene: ``images/NNNN.jpg`` and ``gt_dense_cameras/NNNN.jpg.camera``.
A ``.camera`` file holds K (rows 1-3), radial distortion (row 4), the
camera-to-world rotation (rows 5-7), the centre (row 8) and the image size
(row 9); projection ``x ~ K Rᵀ (X − C)``.

:func:`read_strecha_scene` gives the scene as a :class:`DatasetScene`
(``colmap-trifocal evaluate strecha <scene>``): the pose is turned into
world-to-camera ``R = Rᵀ_file``, ``t = −R C``; the intrinsics are kept as given
(no pixel-convention shift).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..common.errors import CalibrationError
from .base import DatasetScene, GroundTruthView, parsing, pose_from_camera_to_world, require_dir

#: Environment variable naming the folder that holds ``strecha/`` (default: ../shared/datasets).
DATASETS_ENV = "COLMAP_TRIFOCAL_DATASETS"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class StrechaCamera:
    """Ground truth of one image."""

    K: np.ndarray  # (3, 3)
    rotation: np.ndarray  # (3, 3) camera-to-world
    centre: np.ndarray  # (3,) world
    width: int
    height: int

    @property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy) in pixels."""
        return np.array([self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]])


def read_camera_file(path: Path) -> StrechaCamera:
    """Parse one ``.camera`` file (9 rows of numbers)."""
    try:
        rows = [list(map(float, line.split())) for line in Path(path).read_text().splitlines()]
        rows = [r for r in rows if r]
        K = np.array(rows[0:3])
        rotation = np.array(rows[4:7])
        centre = np.array(rows[7])
        width, height = int(rows[8][0]), int(rows[8][1])
    except (OSError, ValueError, IndexError) as exc:
        raise CalibrationError(f"cannot read Strecha camera file {path}: {exc}") from None
    return StrechaCamera(K=K, rotation=rotation, centre=centre, width=width, height=height)


def scene_images(scene: Path) -> list[str]:
    """Image names of a scene (sorted; non-image files such as K.txt are skipped)."""
    return sorted(
        p.name for p in (Path(scene) / "images").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
    )


def ground_truth(scene: Path) -> dict[str, StrechaCamera]:
    """Image name -> ground-truth camera for every image of a scene."""
    folder = Path(scene) / "gt_dense_cameras"
    return {name: read_camera_file(folder / f"{name}.camera") for name in scene_images(scene)}


def ground_truth_intrinsics(scene: Path) -> np.ndarray:
    """(fx, fy, cx, cy) shared by all images of a scene (the mean over images)."""
    return np.mean([c.intrinsics for c in ground_truth(scene).values()], axis=0)


def default_datasets_root(project_root: Path) -> Path:
    """``$COLMAP_TRIFOCAL_DATASETS`` or ``<project>/../shared/datasets``."""
    env = os.environ.get(DATASETS_ENV)
    return Path(env) if env else Path(project_root).resolve().parent / "shared" / "datasets"


def read_strecha_scene(path: Path | str) -> DatasetScene:
    """A scene folder with ``images/`` and ``gt_dense_cameras/`` as a :class:`DatasetScene`."""
    scene = require_dir(path, "Strecha scene folder")
    with parsing(scene, "Strecha scene"):
        cameras = ground_truth(scene)
        if not cameras:
            raise CalibrationError(f"no images in {scene / 'images'}")
        poses = pose_from_camera_to_world(
            np.stack([c.rotation for c in cameras.values()]),
            np.stack([c.centre for c in cameras.values()]),
        )
        views = [
            GroundTruthView(
                name=name,
                intrinsics=camera.intrinsics,
                width=camera.width,
                height=camera.height,
                rotation=pose[:, :3],
                translation=pose[:, 3],
            )
            for (name, camera), pose in zip(cameras.items(), poses, strict=True)
        ]
    return DatasetScene(kind="strecha", name=scene.name, image_dir=scene / "images", views=views)
