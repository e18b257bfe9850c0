"""DTU MVS scenes (Jensen et al., CVPR 2014) in the IDR / NeuS layout.

Kind ``dtu``; ``path`` is a scene folder (e.g. ``dtu_scan24``) holding the images
in ``image/`` (sorted: ``000000.png``, ...) and ``cameras.npz`` or
``cameras_sphere.npz`` with ``world_mat_<i>`` for the i-th image: the 4x4
projection ``K [R | t]`` padded with ``0 0 0 1`` (``scale_mat_<i>`` is ignored, so
the poses are in DTU's own world frame, millimetres).

Each ``world_mat[:3, :4]`` is split with ``cv2.decomposeProjectionMatrix``; K is
normalised to ``K[2, 2] = 1`` with positive fx and fy (the sign flips are moved
into R, which is kept a proper rotation) and ``t = −R C``. DTU's matrices are in
the OpenCV pixel convention: cx, cy + 0.5. Width and height come from the first
image.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..common.errors import CalibrationError
from .base import (
    DatasetScene,
    GroundTruthView,
    from_opencv,
    image_size,
    list_images,
    parsing,
    require_dir,
)

CAMERA_FILES = ("cameras.npz", "cameras_sphere.npz")


def read_dtu_scene(path: Path | str) -> DatasetScene:
    """A DTU scene folder (IDR / NeuS layout) as a :class:`DatasetScene`."""
    scene = require_dir(path, "DTU scene folder")
    image_dir = scene / "image"
    names = list_images(image_dir)
    if not names:
        raise CalibrationError(f"no images in {image_dir}")
    camera_file = next((scene / f for f in CAMERA_FILES if (scene / f).is_file()), None)
    if camera_file is None:
        raise CalibrationError(f"no {' or '.join(CAMERA_FILES)} in {scene}")
    with parsing(camera_file, "DTU camera file"):
        with np.load(camera_file) as data:
            matrices = [np.asarray(data[f"world_mat_{i}"], dtype=float) for i in range(len(names))]
        cameras = [decompose_projection(m[:3, :4]) for m in matrices]
    width, height = image_size(image_dir / names[0]) or (None, None)
    views = [
        GroundTruthView(
            name=name,
            intrinsics=from_opencv(K),
            width=width,
            height=height,
            rotation=R,
            translation=t,
        )
        for name, (K, R, t) in zip(names, cameras, strict=True)
    ]
    return DatasetScene(kind="dtu", name=scene.name, image_dir=image_dir, views=views)


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, R, t) with ``P ~ K [R | t]``, ``K[2, 2] = 1``, fx, fy > 0 and det R = +1."""
    K, R, centre = cv2.decomposeProjectionMatrix(np.asarray(P, dtype=float))[:3]
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    K, R = K * signs, signs[:, None] * R  # K D and D R with D = diag(signs), D² = I
    if np.linalg.det(R) < 0:  # P = −K (−R) [...]: the overall sign of P is free
        R = -R
    K = K / K[2, 2]
    if abs(centre[3, 0]) < 1e-12:
        raise ValueError("camera at infinity")
    t = -R @ (centre[:3, 0] / centre[3, 0])
    return K, R, t
