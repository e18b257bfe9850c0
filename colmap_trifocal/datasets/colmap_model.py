"""A COLMAP model (``cameras``, ``images``, ``points3D``; ``.bin`` or ``.txt``) as ground truth.

Kind ``colmap``; ``path`` is the model folder, typically ``<scene>/sparse/0``.
The images are looked up in ``image_dir`` (default: ``<model>/../../images`` if it
exists, else ``<model>/../images``). Every registered image becomes a view, sorted
by name, with the intrinsics of its camera: (f, f, cx, cy) for the single-focal
models (SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, ...), (fx, fy, cx, cy) for the
others (PINHOLE, OPENCV, FULL_OPENCV, ...); distortion parameters are ignored.
The model is in COLMAP's pixel convention already: no shift. Poses are COLMAP's
``cam_from_world``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from ..common.errors import CalibrationError
from ..database.model_files import check_binary_model
from .base import DatasetScene, GroundTruthView, one_line, require_dir

#: Folder names skipped when naming the scene after the model's location.
_MODEL_FOLDERS = {"sparse", "model", "models"}


def read_colmap_scene(path: Path | str, image_dir: Path | str | None = None) -> DatasetScene:
    """The registered images of a COLMAP model folder, sorted by name."""
    model = require_dir(path, "COLMAP model folder")
    check_binary_model(model)  # before pycolmap, which trusts the counts in the files
    try:
        reconstruction = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError, MemoryError, IndexError) as exc:
        raise CalibrationError(f"cannot read COLMAP model {model}: {one_line(exc)}") from None
    images = sorted(
        (reconstruction.image(i) for i in reconstruction.reg_image_ids()), key=lambda im: im.name
    )
    if not images:
        raise CalibrationError(f"COLMAP model {model} has no registered images")
    views = []
    for image in images:
        camera = reconstruction.camera(image.camera_id)
        pose = image.cam_from_world()
        views.append(
            GroundTruthView(
                name=image.name,
                intrinsics=np.array(
                    [
                        camera.focal_length_x,
                        camera.focal_length_y,
                        camera.principal_point_x,
                        camera.principal_point_y,
                    ]
                ),
                width=int(camera.width),
                height=int(camera.height),
                rotation=pose.rotation.matrix(),
                translation=np.asarray(pose.translation),
            )
        )
    return DatasetScene(
        kind="colmap",
        name=_scene_name(model),
        image_dir=Path(image_dir) if image_dir is not None else default_image_dir(model),
        views=views,
    )


def default_image_dir(model: Path) -> Path:
    """``<model>/../../images`` if it exists, else ``<model>/../images``."""
    model = Path(model).resolve()
    two_up = model.parent.parent / "images"
    return two_up if two_up.is_dir() else model.parent / "images"


def _scene_name(model: Path) -> str:
    folder = Path(model).resolve()
    while folder.parent != folder and (folder.name.isdigit() or folder.name in _MODEL_FOLDERS):
        folder = folder.parent
    return folder.name or str(folder)
